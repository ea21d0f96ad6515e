"""socmon's runtime: the agent, world and monitor processes, whole runs, and the command line.

:mod:`agent` sits above :mod:`design` (numerics) and :mod:`broker_free_net` (transport) and
may import both; those two never import :mod:`agent` nor each other. Inside, a
sub-package imports only from a lower layer or its own (``LAYERS``;
``tests/test_layers.py`` checks every import):

0. :mod:`agent.protocol` what the processes say to each other: topics' messages
   (:mod:`~agent.protocol.wire`), every period and timeout (:mod:`~agent.protocol.timing`),
   signed control messages, the run manifest. :mod:`agent.shell` what every process
   shell shares (a log a flood cannot fill, heap trimming).
1. The three roles, each a state machine that never touches a socket (``core``) and the
   process shell that feeds it from a zenoh peer (``process``): :mod:`agent.node` (an
   agent: what it uses for a late or silent neighbour, how it takes a role),
   :mod:`agent.world` (the social system and the clock), :mod:`agent.monitor` (the failure
   detector, the reassignment of roles, the gain worker). :mod:`agent.testbed` network
   namespaces as hosts.
2. :mod:`agent.run` whole runs: a live run on this machine (launcher, faults), the same
   runtime under simulated time (:mod:`~agent.run.simulated`), the recorder, the run
   folder (:mod:`~agent.run.folder`, its only writer) and its summary, chaos schedules
   and their invariants, ``watch``.
3. :mod:`agent.cli` the ``socmon`` command line: a module per command.
"""

#: sub-package -> layer; a module imports only from its own layer or a lower one
LAYERS = {
    "protocol": 0,
    "shell": 0,
    "node": 1,
    "world": 1,
    "monitor": 1,
    "testbed": 1,
    "run": 2,
    "cli": 3,
}
