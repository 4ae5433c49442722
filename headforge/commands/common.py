"""What every command shares: the console, progress lines and bars, head-model options."""

from __future__ import annotations

import time
from typing import Optional

import typer
from rich.console import Console

console = Console(stderr=True)

MODEL_OPT = typer.Option("open-head", "--model", "-m", help="open-head (built in) or flame (your own files)")
FLAME_OPT = typer.Option(None, "--flame-dir", help="folder with FLAME's generic_model.pkl (or HEADFORGE_FLAME_DIR)")


def progress(message: str) -> None:
    console.print(f"[dim]{time.strftime('%H:%M:%S')}[/] {message}")


class Bars:
    """Rich progress bars; ``factory(description, total)`` returns a no-argument advance callable."""

    def __enter__(self):
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        self.progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                                 console=console, transient=True)
        self.progress.__enter__()
        return self

    def __exit__(self, *exc):
        return self.progress.__exit__(*exc)

    def factory(self, description: str, total):
        task = self.progress.add_task(description, total=total)
        return lambda: self.progress.advance(task)


def load_model(name: str, flame_dir: Optional[str]):
    from headforge.head import create

    return create(name, flame_dir=flame_dir, progress=progress)
