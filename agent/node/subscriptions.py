"""Whose estimates an agent subscribes to: its in-neighbours, not the whole network.

One rule (:func:`estimate_sources`), read by the agent process after every change of
role (:mod:`agent.node.process`); docs/transport.md says why each case is there:

- an agent with a role hears its in-neighbours (``role.neighbours``) and the failed
  agents whose stream a new neighbour continues (``role.continues``: the continuity rule
  reads that agent's last estimates on the new link);
- with an assignment pending it also hears the pending role's in-neighbours, the agents
  those continue, and the agent it takes over, from the moment the assignment is
  accepted: the lead steps before ``activate_at`` are the subscription's head start, and
  each agent's estimate publisher keeps its last ``AgentCore.history`` estimates for a
  receiver that subscribes late (:func:`agent.protocol.topics.estimate_subscriptions`);
- a standby (no role) hears every agent: it may be told to take over any of them and
  then starts from that agent's freshest estimate, so it must already hold it.

Traffic: an active agent receives ``deg_in`` estimates a step instead of ``N - 1``; the
standbys still receive ``N - 1`` each (there are few of them).

>>> from types import SimpleNamespace as R
>>> active = R(role=R(neighbours={1: .3, 3: .2}, continues={}), pending=None, id=2)
>>> sorted(estimate_sources(active))
[1, 3]
>>> switching = R(role=active.role, id=2,
...               pending=R(neighbours={3: .5}, continues={3: 1}, take_over=None))
>>> sorted(estimate_sources(switching))
[1, 3]
>>> estimate_sources(R(role=None, pending=None, id=4)) is None
True
"""

from __future__ import annotations

__all__ = ["estimate_sources", "role_sources"]


def role_sources(role) -> set:
    """The agents a role reads estimates of: its in-neighbours and, for a new neighbour
    that takes over a failed agent's row, that failed agent (the continuity rule)."""
    return set(role.neighbours) | set((role.continues or {}).values())


def estimate_sources(core):
    """The agent ids whose estimates ``core`` (an :class:`agent.node.core.AgentCore`) must
    receive now, as a frozenset, or None for every agent (a standby).

    A standby with an assignment pending still hears everyone until the role is in force:
    its first estimate comes from the freshest one of the agent it takes over, and its
    in-neighbours' estimates up to the activation are already in hand."""
    if core.role is None:
        return None
    ids = role_sources(core.role)
    if core.pending is not None:
        ids |= role_sources(core.pending)
        if getattr(core.pending, "take_over", None):
            ids.add(core.pending.take_over)     # its first estimate starts from that one
    ids.discard(core.id)
    return frozenset(ids)
