"""``python -m agent.cli``: the ``socmon`` program (:func:`agent.cli.main.run_program`)."""

if __name__ == "__main__":   # not when a spawned worker re-imports the parent's main module
    from agent.cli.main import run_program

    run_program()
