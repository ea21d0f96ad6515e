"""Testbeds: :mod:`~agent.testbed.netns` network namespaces, one per process of a run, as
separate hosts."""
