"""``socmon agent SCENARIO --id I``: one agent process of a live run."""

from __future__ import annotations

HELP = "run one agent: the shared estimator step every step, over zenoh"


def add_arguments(parser) -> None:
    from broker_free_net.config import add_net_arguments

    from agent.cli._common import add_force_gains_argument, add_manifest_argument, add_scenario_argument

    add_scenario_argument(parser)
    parser.add_argument("--id", type=int, required=True,
                        help="agent id (1..N active, N+1.. standby agents of the scenario)")
    parser.add_argument("--gains", help="gains file (.npz); default: design with the default "
                                        "method (every agent designs the same gain)")
    add_force_gains_argument(parser)
    parser.add_argument("--seed", type=int, default=0, help="run seed (same as the world's)")
    parser.add_argument("--delays", default="scenario",
                        help="link delays injected at start (receiver side): scenario, none "
                             "or uniform:T (default: scenario)")
    parser.add_argument("--deadline-ms", type=float, default=None,
                        help="wait this long after a step's readings for late neighbour "
                             "estimates (default: the step period)")
    parser.add_argument("--drop", type=float, default=0.0,
                        help="probability that an estimate is lost on a link, drawn from the run "
                             "seed as the simulator draws it (default 0)")
    parser.add_argument("--lie", default=None, metavar="STEP:SIZE",
                        help="scripted misbehaviour: from STEP on, publish estimates SIZE "
                             "measurement-noise std-devs off on every component, the agent's "
                             "own estimate staying honest (socmon up --fault lie uses it)")
    parser.add_argument("--crash-at", type=int, default=None, metavar="STEP",
                        help="scripted crash: publish step STEP-1, then SIGKILL itself "
                             "(reproducible failures; socmon up --kill uses it)")
    add_manifest_argument(parser)
    add_net_arguments(parser)


def run(args) -> int:
    from agent.cli._common import CommandError, run_command

    def body():
        from design.errors import ScenarioError
        from design.scenario import resolve_delays

        from agent.node.process import run_agent
        from agent.node.core import agent_config
        from agent.cli._common import check_run_flags, gains_for, load_scenario_arg, net_config_arg

        check_run_flags(args)
        scenario = load_scenario_arg(args.scenario)
        verifier = operator_verifier = None
        if args.manifest:
            from agent.protocol.control_auth import ControlVerifier
            from agent.protocol.manifest import ManifestMismatch, check_manifest, public_key

            try:
                manifest = check_manifest(args.manifest, scenario, args.gains, args.seed,
                                          args.delays)
                control = public_key(manifest, "control_public_key")
                operator = public_key(manifest, "operator_public_key")
            except ManifestMismatch as exc:
                raise CommandError(str(exc)) from None
            try:
                if control is not None:
                    verifier = ControlVerifier(control, manifest["run"])
                if operator is not None:
                    operator_verifier = ControlVerifier(operator, manifest["run"])
            except ValueError as exc:
                raise CommandError(f"--manifest: not an Ed25519 public key: {exc}") from None
        M = scenario.N + scenario.standby
        if not 1 <= args.id <= M:
            raise CommandError(f"--id: no agent {args.id} (agents 1..{scenario.N}"
                               + (f", standby {scenario.N + 1}..{M}" if scenario.standby else "")
                               + ")")
        try:
            delays = resolve_delays(scenario, args.delays)
        except ScenarioError as exc:
            raise CommandError(str(exc)) from None
        G = gains_for(scenario, args.gains, delays, args.force_gains) if args.id <= scenario.N else None
        deadline_ms = args.deadline_ms if args.deadline_ms is not None else scenario.step_ms
        if not deadline_ms > 0:
            raise CommandError(f"--deadline-ms: must be > 0, got {deadline_ms}")
        from broker_free_net.security import identity_name

        net = net_config_arg(args, identity=identity_name("agent", args.id))
        if not 0 <= args.drop < 1:
            raise CommandError(f"--drop: must be a probability in [0, 1), got {args.drop}")
        if args.crash_at is not None and args.crash_at < 1:
            raise CommandError(f"--crash-at: must be a step >= 1, got {args.crash_at}")
        config = agent_config(scenario, args.id, G, args.seed, delays, deadline_ms / 1000.0,
                              impair_seed=args.seed * 1000 + args.id, drop=args.drop,
                              residuals=args.drop == 0, lie=parse_lie(args.lie, args.id))
        return run_agent(config, net, crash_at=args.crash_at, verifier=verifier,
                         operator_verifier=operator_verifier)

    return run_command(body)


def parse_lie(text, agent: int):
    """``--lie STEP:SIZE`` -> :class:`design.simulate.Fault` (kind ``lie``), or None."""
    if text is None:
        return None
    from design.simulate import Fault

    from agent.cli._common import CommandError, parse_int

    step, sep, size = str(text).partition(":")
    try:
        value = float(size)
    except ValueError:
        value = -1.0
    if not sep or not 0 <= value <= 1e6:
        raise CommandError(f"--lie: expected STEP:SIZE with SIZE in [0, 1e6], got {text!r}")
    return Fault("lie", agent - 1, parse_int(step, "--lie STEP", lo=1), value)
