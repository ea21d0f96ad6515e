"""The world: :mod:`~agent.world.core` the social system stepped one step at a time,
:mod:`~agent.world.process` the process that is the clock of a live run and publishes the
truth and the sensor readings."""
