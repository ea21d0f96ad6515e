import doctest

import pytest

from broker_free_net import codec, config, impair, keys, peer


@pytest.mark.parametrize("module", [codec, config, impair, keys, peer], ids=lambda m: m.__name__)
def test_docstring_examples(module):
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS)
    assert result.failed == 0
