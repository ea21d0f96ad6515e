"""``socmon keys``: make and inspect the key material of a secured run.

``socmon keys init DIR --scenario S --run R`` makes a CA, a certificate and key for every
process of the run (world, agent-1..agent-M with M = N + standby, monitor, operator,
recorder) and each process's zenoh config (TLS with mutual authentication, access control
with default deny), and records scenario S (name, digest, agents). Processes then take
``--keys DIR`` and refuse it with another scenario. Make a new DIR for every run: the
CA's private key is not kept, so a key set cannot be extended or reused by mistake.

Examples::

    socmon keys init run7-keys --scenario paper-14 --run run7
    socmon keys init run7-keys --scenario paper-14 --run run7 --host 10.0.0.5 --port-base 7500
    socmon keys show run7-keys
"""

from __future__ import annotations

from agent.cli._common import (CommandError, add_json_argument, int_flag, load_scenario_arg,
                               print_json, run_command)

HELP = "make (init) or show the certificates and zenoh security configs of a run"


def add_arguments(parser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    p = sub.add_parser("init", help="make a new key set for one run",
                       description="Make a new key set for one run (see docs/security.md).")
    p.add_argument("dir", metavar="DIR", help="directory to create (must not exist or be empty)")
    p.add_argument("--scenario", required=True,
                   help="scenario TOML file or built-in name: fixes the agents 1..N+standby "
                        "and is recorded (the processes refuse the keys for another)")
    p.add_argument("--run", default="default", help="run id the keys are for (default 'default')")
    p.add_argument("--host", action="append", metavar="ADDR",
                   help="address of a machine of the run, written into the certificates "
                        "(repeatable; default 127.0.0.1); the first is the host of --port-base")
    p.add_argument("--port-base", type=int_flag(lo=1, hi=65535), default=None, metavar="PORT",
                   help="write endpoints into each config: process k listens on "
                        "tls/HOST:PORT+k and connects to the world's (default: endpoints "
                        "come from --listen/--connect)")
    p.add_argument("--valid-days", type=int_flag(lo=1, hi=3650), default=30,
                   help="validity of the certificates in days (default 30)")
    add_json_argument(p, "print the manifest as JSON")
    p = sub.add_parser("show", help="print the manifest of a key set")
    p.add_argument("dir", metavar="DIR")
    add_json_argument(p, "print the manifest as JSON")


def run(args) -> int:
    def body():
        import json
        from pathlib import Path

        from agent.protocol.topics import key_set_lines, make_run_keys, run_identities
        from broker_free_net.security import InvalidKeys, load_key_set

        flag = {"dir": "DIR", "run": "--run", "hosts": "--host", "port_base": "--port-base",
                "valid_days": "--valid-days", "keys": "DIR"}
        try:
            if args.action == "init":
                scenario = load_scenario_arg(args.scenario)
                ks = make_run_keys(args.dir, args.run, run_identities(scenario.N + scenario.standby),
                                   scenario, hosts=tuple(args.host or ("127.0.0.1",)), port_base=args.port_base,
                                   valid_days=args.valid_days)
            else:
                ks = load_key_set(args.dir)
        except InvalidKeys as exc:
            message = str(exc).removeprefix(f"{exc.field}: ")
            raise CommandError(f"{flag.get(exc.field, exc.field)}: {message}") from None
        manifest = json.loads((Path(ks.dir) / "keys.json").read_text())
        manifest["dir"] = str(ks.dir)
        if args.json:
            print_json(manifest)
            return 0
        print("\n".join(key_set_lines(ks, manifest.get("endpoints") or {})))
        return 0

    return run_command(body)
