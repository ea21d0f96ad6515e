"""``socmon init [PATH] [--schema FILE] [--force]``: write a commented starter scenario."""

from __future__ import annotations

HELP = "write a commented starter scenario (TOML) to edit; the format is in docs/scenario.md"


def add_arguments(parser) -> None:
    parser.add_argument("path", nargs="?", default="scenario.toml",
                        help="where to write the scenario (default scenario.toml)")
    parser.add_argument("--schema", metavar="FILE",
                        help="also write the scenario's JSON Schema to FILE and name it in a "
                             "'#:schema' first line, for TOML editors (taplo, Even Better TOML)")
    parser.add_argument("--force", action="store_true", help="overwrite existing files")


def run(args) -> int:
    from agent.cli._common import run_command

    return run_command(lambda: _init(args))


def _init(args) -> int:
    import json
    import os
    from pathlib import Path

    from design.scenario import scenario_schema, starter_scenario_toml

    from agent.cli._common import CommandError

    path = Path(args.path)
    text = starter_scenario_toml(args.path)
    targets = [(path, "PATH")]
    if args.schema:
        schema_path = Path(args.schema)
        targets.append((schema_path, "--schema"))
        rel = os.path.relpath(schema_path.resolve(), path.resolve().parent)
        text = f"#:schema {Path(rel).as_posix()}\n" + text
    for target, flag in targets:
        if target.exists() and not args.force:
            raise CommandError(f"{flag}: {str(target)!r} exists (--force to overwrite)")
        if not target.resolve().parent.is_dir():
            raise CommandError(f"{flag}: no directory {str(target.resolve().parent)!r}")
    try:
        if args.schema:
            schema_path.write_text(json.dumps(scenario_schema(), indent=2) + "\n")
        path.write_text(text)
    except OSError as exc:
        raise CommandError(f"cannot write {exc.filename!r}: {exc.strerror}") from None
    print(f"wrote {path}; try: socmon analyze {path}")
    return 0
