"""The ``socmon`` command line: one subcommand per module of :mod:`agent.cli`.

Each command module defines ``HELP`` (one line), ``add_arguments(parser)`` and
``run(args) -> int``; the heavy imports (cvxpy, matplotlib, and zenoh where a command
does not need it to build its flags) happen inside the functions that use them. Exit
status: 0 success, 1 the command ran but the result is negative (e.g. no stabilising
gain), 2 bad input (named in the message, argparse's rejections included), 130
interrupted, 141 stdout closed by its reader (``socmon certify ... | head``; nothing printed).
"""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys

# The commands multiply and decompose matrices of a few hundred rows; a multi-threaded BLAS
# on a small shared machine spends its time waiting for its own threads (an order-672
# eigen-decomposition: 0.45 s on one thread, 21 s on two contended ones). One thread unless
# the user says otherwise; set before numpy is first imported.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

#: exit status when the reader of stdout went away (128 + SIGPIPE, as a shell reports it)
EXIT_BROKEN_PIPE = 141

#: subcommand -> module under agent.cli, in the order shown by --help
COMMANDS = {
    "init": "init",
    "analyze": "analyze",
    "plan": "plan",
    "certify": "certify",
    "design": "design_cmd",
    "simulate": "simulate",
    "reproduce": "reproduce",
    "world": "world",
    "agent": "agent_cmd",
    "up": "up",
    "watch": "watch",
    "inject": "inject",
    "monitor": "monitor",
    "chaos": "chaos",
    "keys": "keys",
    "router": "router",
}


def _version() -> str:
    """The installed distribution's version (a source tree not installed: unknown)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("socmon")
    except PackageNotFoundError:
        return "(not installed)"


class _CommandParser(argparse.ArgumentParser):
    """A command's parser: a flag it rejects is one line naming it (the README's promise),
    with where the usage is, instead of the whole usage block first."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see `{self.prog} --help`)\n")

    def parse_known_args(self, args=None, namespace=None):
        """Every argument after the command is the command's: one it does not know is
        its error (``socmon up: error: unrecognized arguments: --stepz``), not the top
        level's usage."""
        namespace, extras = super().parse_known_args(args, namespace)
        if extras:
            self.error(f"unrecognized arguments: {' '.join(extras)}")
        return namespace, extras


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="socmon",
        description="Resilient distributed monitoring of social dynamics by collaborating agents.",
    )
    parser.add_argument("--version", action="version", version=f"socmon {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND",
                                parser_class=_CommandParser)
    sub.required = True
    for name, module_name in COMMANDS.items():
        try:
            module = importlib.import_module(f"agent.cli.{module_name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"agent.cli.{module_name}":
                continue  # command not part of this build
            raise
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help (0) or a flag argparse rejects (2, message printed)
        return exc.code if isinstance(exc.code, int) else 2
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        print("socmon: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # the reader went away (`socmon certify ... | head`): stop quietly, as a shell
        # command killed by SIGPIPE would; stdout is pointed at devnull so that the
        # interpreter's final flush does not raise a second time
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return EXIT_BROKEN_PIPE


class LossyStream:
    """A text stream whose writes never raise for want of room: a full disk (or any other
    I/O error but a broken pipe) loses the text, counted in ``lost``, instead of killing
    the process that logs. A process's log is its least important output.

    >>> import io
    >>> class Full(io.StringIO):
    ...     def write(self, text):
    ...         raise OSError(28, "No space left on device")
    >>> s = LossyStream(Full())
    >>> s.write("step 3"), s.lost
    (6, 6)
    """

    def __init__(self, stream):
        self._stream = stream
        self.lost = 0

    def write(self, text):
        try:
            return self._stream.write(text)
        except BrokenPipeError:
            raise
        except OSError:
            self.lost += len(text)
            return len(text)

    def flush(self):
        try:
            self._stream.flush()
        except BrokenPipeError:
            raise
        except OSError:
            pass

    def __getattr__(self, name):
        return getattr(self._stream, name)


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def run_program() -> None:
    """The program (``socmon``, ``python -m agent.cli``): :func:`main`, then exit with its
    status.

    The interpreter's shutdown puts SIGTERM and SIGINT back to their default action, so
    one that arrived then killed the process (status -15) instead of letting it exit with
    its own: ``up`` stops its children at the end of a run, when the world may already be
    shutting down (seen once in a chaos run). Once :func:`main` has returned the work is
    done, and both signals are ignored while the process exits.

    Until a command handles SIGTERM itself it ends the command as Ctrl-C does.
    Standard output and error are :class:`LossyStream`: a process whose log sits on a full
    disk keeps running (``up`` says the disk is full when it writes the run folder).
    """
    if sys.stdout is not None:
        sys.stdout = LossyStream(sys.stdout)
    if sys.stderr is not None:
        sys.stderr = LossyStream(sys.stderr)
    # SIGTERM as Ctrl-C ("socmon: interrupted", 130) for the commands that do not handle
    # it themselves (inject, reproduce, design, ...): killed by it, they said nothing
    signal.signal(signal.SIGTERM, _interrupt)
    code = main()
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    sys.exit(code)


if __name__ == "__main__":
    run_program()
