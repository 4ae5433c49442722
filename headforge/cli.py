"""The ``headforge`` command line (typer): wires the command groups of :mod:`headforge.commands`.
Every user-facing error is one line, exit code 1."""

from __future__ import annotations

import os
import sys

import typer

from headforge.commands import batch, craft, demo, evaluate, export, fit, model, render, synth, track, view
from headforge.commands.common import console
from headforge.errors import HeadforgeError

app = typer.Typer(help="headforge: animatable 3D head avatars from phone videos or head scans.",
                  no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False)
app.add_typer(model.app, name="model")
app.add_typer(render.app, name="render")
app.add_typer(craft.app, name="craft")
app.add_typer(batch.app, name="batch")
app.command("track")(track.track)
app.command("fit")(fit.fit)
app.command("export")(export.export)
app.command("synth")(synth.synth)
app.command("eval")(evaluate.evaluate)
app.command("demo")(demo.demo)
app.command("view")(view.view)


def main() -> None:
    import warnings

    # mediapipe 0.10.14 calls a protobuf API that warns on every start; nothing for users to act on
    warnings.filterwarnings("ignore", message="SymbolDatabase.GetPrototype")
    os.environ.setdefault("GLOG_minloglevel", "2")
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")
    try:
        app()
    except HeadforgeError as exc:
        console.print(f"[red]error:[/] {exc}")
        sys.exit(1)
    except KeyboardInterrupt:
        console.print("[red]interrupted[/]")
        sys.exit(130)


if __name__ == "__main__":
    main()
