"""Write the built-in scenarios of the scale benchmark: communities-16 and communities-32.

They are :func:`design.generate.communities_scenario` with N = 16 and 32 (seed N), written
out in full by :func:`design.scenario.scenario_to_toml`, so that a run needs no generator
and a reader sees every weight. ``tests/test_generate.py`` checks that the files equal the
generator's output.

Usage::

    python scripts/make_scale_scenarios.py [--out design/scenarios]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

#: Agents of each built-in scale scenario (the seed of its weights is N).
SIZES = (16, 32)


def main(argv=None) -> int:
    from design.generate import communities_scenario
    from design.scenario import scenario_from_dict, scenario_to_toml

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(ROOT / "design" / "scenarios"))
    args = parser.parse_args(argv)
    for N in SIZES:
        scenario = scenario_from_dict(communities_scenario(N, seed=N), source=f"communities-{N}")
        path = Path(args.out) / f"{scenario.name}.toml"
        text = scenario_to_toml(scenario).replace(
            f"# written by socmon from communities-{N}",
            f"# {N} communities of 2 and a public of 4 (design.generate.communities_scenario, "
            f"seed {N});\n# written by scripts/make_scale_scenarios.py: regenerate, do not edit")
        path.write_text(text)
        print(f"{path}: n = {scenario.n}, N = {scenario.N}, rho(A) = {scenario.rho_A:.4g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
