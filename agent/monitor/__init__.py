"""The monitor: :mod:`~agent.monitor.core` the failure detector (liveliness, status pace,
hearsay) and the reassignment of failed agents' roles to equivalent standbys, as a state
machine; :mod:`~agent.monitor.gain_worker` the processes that design the new gains;
:mod:`~agent.monitor.process` the process shell."""
