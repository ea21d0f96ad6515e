"""What the processes of a run say to each other and agree on.

:mod:`~agent.protocol.wire` the messages and their schemas, :mod:`~agent.protocol.timing`
every period and timeout with the relations between them, :mod:`~agent.protocol.control_auth`
signed control messages, :mod:`~agent.protocol.manifest` what every process checks at start-up,
:mod:`~agent.protocol.topics` the key expressions of a run, the process roles and their rights.
"""
