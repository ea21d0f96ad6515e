"""The agent process that ``socmon agent``'s flags ask for, checked, and its start.

:func:`agent_options` turns the flags into :class:`AgentOptions`: the agent's
:class:`agent.node.core.AgentConfig` (its role, gains, delays, deadline, impairments and
scripted lie), the transport, the scripted crash and the verifiers of signed control
messages the run's manifest names. Every problem is an
:class:`~agent.run.inputs.InputError` (exit 2) naming the flag; the first one found
wins, in this order: ``--seed``, the scenario, ``--manifest``, ``--id``, ``--delays``,
the gains (loaded, or designed when ``--gains`` is not given), ``--deadline-ms``, the
transport flags, ``--drop``, ``--crash-at``, ``--lie``. :func:`start_agent` runs the
process until it ends.
"""

from __future__ import annotations

from dataclasses import dataclass

from design.errors import ScenarioError
from design.scenario import resolve_delays

from agent.run.inputs import (InputError, check_keys_arg, check_run_flags, gains_for,
                              load_scenario_arg)

__all__ = ["AgentOptions", "agent_options", "manifest_verifiers", "check_agent_id",
           "parse_lie", "parse_sensor_fault", "start_agent"]


@dataclass(frozen=True)
class AgentOptions:
    """What ``socmon agent`` runs, checked: the agent of ``config`` (an
    :class:`agent.node.core.AgentConfig`) in the run of ``net`` (a
    :class:`broker_free_net.config.NetConfig`); ``crash_at``: the step of
    ``--crash-at`` (None: none); ``verifier`` and ``operator_verifier``: the
    :class:`agent.protocol.control_auth.ControlVerifier` of the run's control and
    operator keys (None: the run signs nothing)."""

    config: object
    net: object
    crash_at: int | None
    verifier: object
    operator_verifier: object


def agent_options(args, *, net_config_arg, parse_int) -> AgentOptions:
    """The :class:`AgentOptions` of ``socmon agent``'s ``args``.

    ``net_config_arg(args, identity=...)`` reads the transport flags and
    ``parse_int(text, flag, lo=...)`` the step of ``--lie``: the command line's readers
    (:mod:`agent.cli._common`), passed in since a run does not import the command line.
    InputError naming the first bad flag, in the order of the module's docstring.
    """
    from agent.protocol.topics import identity_name

    from agent.node.core import agent_config

    check_run_flags(args)
    scenario = load_scenario_arg(args.scenario)
    verifier = operator_verifier = None
    if args.manifest:
        verifier, operator_verifier = manifest_verifiers(args.manifest, scenario, args.gains,
                                                         args.seed, args.delays)
    check_agent_id(scenario, args.id)
    try:
        delays = resolve_delays(scenario, args.delays)
    except ScenarioError as exc:
        raise InputError(str(exc)) from None
    G = gains_for(scenario, args.gains, delays, args.force_gains) if args.id <= scenario.N \
        else None
    deadline_ms = args.deadline_ms if args.deadline_ms is not None else scenario.step_ms
    if not deadline_ms > 0:
        raise InputError(f"--deadline-ms: must be > 0, got {deadline_ms}")
    net = net_config_arg(args, identity=identity_name("agent", args.id))
    check_keys_arg(net.keys, scenario)
    if not 0 <= args.drop < 1:
        raise InputError(f"--drop: must be a probability in [0, 1), got {args.drop}")
    if args.crash_at is not None and args.crash_at < 1:
        raise InputError(f"--crash-at: must be a step >= 1, got {args.crash_at}")
    config = agent_config(scenario, args.id, G, args.seed, delays, deadline_ms / 1000.0,
                          impair_seed=args.seed * 1000 + args.id, drop=args.drop,
                          residuals=args.drop == 0,
                          lie=parse_lie(args.lie, args.id, parse_int),
                          sensor_faults=[parse_sensor_fault(text, args.id, parse_int)
                                         for text in getattr(args, "sensor_fault", [])])
    return AgentOptions(config=config, net=net, crash_at=args.crash_at, verifier=verifier,
                        operator_verifier=operator_verifier)


def manifest_verifiers(manifest, scenario, gains, seed, delays) -> tuple:
    """``(verifier, operator_verifier)``: the
    :class:`agent.protocol.control_auth.ControlVerifier` of the control and the operator
    public keys of the run's ``manifest`` file (each None when the run has none), once
    the manifest is checked against ``scenario``, ``gains`` (a path or None), ``seed`` and
    ``delays`` (the ``--delays`` text); InputError naming ``--manifest`` otherwise."""
    from agent.protocol.control_auth import ControlVerifier
    from agent.protocol.manifest import ManifestMismatch, check_manifest, public_key

    verifier = operator_verifier = None
    try:
        data = check_manifest(manifest, scenario, gains, seed, delays)
        control = public_key(data, "control_public_key")
        operator = public_key(data, "operator_public_key")
    except ManifestMismatch as exc:
        raise InputError(str(exc)) from None
    try:
        if control is not None:
            verifier = ControlVerifier(control, data["run"])
        if operator is not None:
            operator_verifier = ControlVerifier(operator, data["run"])
    except ValueError as exc:
        raise InputError(f"--manifest: not an Ed25519 public key: {exc}") from None
    return verifier, operator_verifier


def check_agent_id(scenario, agent: int) -> None:
    """InputError naming ``--id`` unless ``agent`` is an agent of ``scenario``: active
    (1..N) or standby (N+1..N+standby).

    >>> from design.scenario import load_scenario
    >>> check_agent_id(load_scenario("paper-14-live"), 4)
    >>> check_agent_id(load_scenario("paper-14-live"), 5)
    Traceback (most recent call last):
    ...
    agent.run.inputs.InputError: --id: no agent 5 (agents 1..3, standby 4..4)
    """
    M = scenario.N + scenario.standby
    if not 1 <= agent <= M:
        raise InputError(f"--id: no agent {agent} (agents 1..{scenario.N}"
                         + (f", standby {scenario.N + 1}..{M}" if scenario.standby else "")
                         + ")")


def parse_lie(text, agent: int, parse_int):
    """``--lie STEP:SIZE`` of agent ``agent`` (1-based) -> :class:`design.simulate.Fault`
    (kind ``lie``), or None without it; ``parse_int(text, flag, lo=...)`` reads STEP.

    >>> parse_lie("150:2.5", 3, lambda text, flag, lo: int(text))
    Fault(kind='lie', agent=2, start=150, size=2.5, ramp=100, direction=None)
    >>> parse_lie("150", 3, None)
    Traceback (most recent call last):
    ...
    agent.run.inputs.InputError: --lie: expected STEP:SIZE with SIZE in [0, 1e6], got '150'
    """
    if text is None:
        return None
    from design.simulate import Fault

    step, sep, size = str(text).partition(":")
    try:
        value = float(size)
    except ValueError:
        value = -1.0
    if not sep or not 0 <= value <= 1e6:
        raise InputError(f"--lie: expected STEP:SIZE with SIZE in [0, 1e6], got {text!r}")
    return Fault("lie", agent - 1, parse_int(step, "--lie STEP", lo=1), value)


def parse_sensor_fault(text, agent: int, parse_int):
    """``--sensor-fault KIND:STEP:SIZE`` of agent ``agent`` (1-based) ->
    :class:`design.simulate.Fault` (kind ``bias``, ``drift`` or ``noise``);
    ``parse_int(text, flag, lo=...)`` reads STEP.

    >>> parse_sensor_fault("bias:150:5", 3, lambda text, flag, lo: int(text))
    Fault(kind='bias', agent=2, start=150, size=5.0, ramp=100, direction=None)
    >>> parse_sensor_fault("tilt:150:5", 3, None)
    Traceback (most recent call last):
    ...
    agent.run.inputs.InputError: --sensor-fault: expected KIND:STEP:SIZE with KIND one of bias, drift, noise and SIZE in [0, 1e6], got 'tilt:150:5'
    """
    from design.simulate import SENSOR_FAULT_KINDS, Fault

    kind, _, rest = str(text).partition(":")
    step, sep, size = rest.partition(":")
    try:
        value = float(size)
    except ValueError:
        value = -1.0
    if kind not in SENSOR_FAULT_KINDS or not sep or not 0 <= value <= 1e6:
        raise InputError(f"--sensor-fault: expected KIND:STEP:SIZE with KIND one of "
                         f"{', '.join(SENSOR_FAULT_KINDS)} and SIZE in [0, 1e6], got {text!r}")
    return Fault(kind, agent - 1, parse_int(step, "--sensor-fault STEP", lo=1), value)


def start_agent(options: AgentOptions) -> int:
    """Run the agent process of ``options`` until it is stopped or the world leaves
    (:func:`agent.node.process.run_agent`); its exit status."""
    from agent.node.process import run_agent

    return run_agent(options.config, options.net, crash_at=options.crash_at,
                     verifier=options.verifier, operator_verifier=options.operator_verifier)
