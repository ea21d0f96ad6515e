"""An agent: :mod:`~agent.node.core` its state machine (the neighbour policy it applies to a
late or silent neighbour, role assignments, rosters), :mod:`~agent.node.process` the
process that feeds it from a zenoh peer."""
