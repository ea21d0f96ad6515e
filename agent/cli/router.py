"""``socmon router``: a zenoh router that processes join as clients (``--mode client``).

Examples::

    socmon router --listen tcp/0.0.0.0:7447
    socmon agent paper-14-live --id 1 --run r1 --mode client --connect tcp/HOST:7447 ...
    socmon up paper-14-live --router          # every process of a local run through one

A second router joins the first with ``--connect`` (clients list both in their
``--connect`` and use the first that answers). See docs/transport.md for ``zenohd`` and the
zenoh container, the path for production.
"""

from __future__ import annotations

from agent.cli._common import CommandError, add_json_argument, run_command

HELP = "run a zenoh router: processes started with --mode client talk through it"


def add_arguments(parser) -> None:
    from broker_free_net.config import add_net_arguments
    from broker_free_net.router import DEFAULT_ROUTER_LISTEN

    parser.description = (f"{HELP}. It listens on --listen (default {DEFAULT_ROUTER_LISTEN[0]}"
                          f"; port 0: chosen by the OS) and prints its endpoints; --connect "
                          f"joins other routers. It routes every run and stops on SIGTERM or "
                          f"Ctrl-C. Secured runs (--keys) use the peer mesh, not a router.")
    add_json_argument(parser, "print the endpoints as one JSON line")
    add_net_arguments(parser, router_listen=DEFAULT_ROUTER_LISTEN[0])


def run(args) -> int:
    def body():
        import json

        import zenoh

        from broker_free_net.config import InvalidNetConfig, net_config_from_args, zenoh_message
        from broker_free_net.router import DEFAULT_ROUTER_LISTEN, serve_router

        if args.keys is not None:
            raise CommandError("--keys: a router cannot run with keys (the access control of "
                               "a secured run names the process at the other end of a link, "
                               "which a router would hide); secured runs use the peer mesh")
        if args.mode == "client":
            raise CommandError("--mode: a router is not a client")
        if not args.listen:
            args.listen = list(DEFAULT_ROUTER_LISTEN)
        try:
            net = net_config_from_args(args)
        except InvalidNetConfig as exc:
            raise CommandError(exc.as_flag()) from None

        def ready(router):
            endpoints = router.endpoints()
            if args.json:
                print(json.dumps({"zid": router.zid(), "endpoints": endpoints}), flush=True)
            else:
                print(f"router {router.zid()} listening on {', '.join(endpoints)}", flush=True)

        try:
            serve_router(net, on_ready=ready)
        except InvalidNetConfig as exc:
            raise CommandError(exc.as_flag()) from None
        except zenoh.ZError as exc:  # e.g. the port is taken
            raise CommandError(f"cannot start the router: {zenoh_message(exc)}",
                               status=1) from None
        return 0

    return run_command(body)
