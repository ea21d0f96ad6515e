"""socmon's processes: the agent and world state machines and their process shells.

Layers: :mod:`agent` sits above :mod:`design` (numerics) and :mod:`broker_free_net`
(transport) and may import both; those two never import :mod:`agent` nor each other.
Inside, the state machines and shells (:mod:`agent.core`, :mod:`agent.wire`,
:mod:`agent.agent_process`, :mod:`agent.world_process`, :mod:`agent.launcher`) never
import the command line; the command line (:mod:`agent.cli` and :mod:`agent.commands`)
is on top and may import everything. ``tests/test_layers.py`` checks these rules.
"""
