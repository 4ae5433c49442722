"""``headforge craft``: HeadCraft part 1 -- scan sets, registration, UV displacement maps."""

from __future__ import annotations

from pathlib import Path

import typer

from headforge.errors import HeadforgeError

app = typer.Typer(help="HeadCraft: head scans -> registered template with free displacements -> UV displacement maps.",
                  no_args_is_help=True)


def _fail(exc: HeadforgeError) -> None:
    typer.echo(f"error: {exc}", err=True)
    raise typer.Exit(1)


@app.command("scans")
def scans(output: Path = typer.Option(..., "-o", "--output", help="folder to write the scan set into"),
          n: int = typer.Option(8, "--n", help="number of identities (each has a neutral scan; every 3rd an expression scan too)"),
          seed: int = typer.Option(0, "--seed", help="random seed"),
          harder: bool = typer.Option(True, help="cycle the harder variants (remeshed, noisy, holes, out-of-span)"),
          voxel_mm: float = typer.Option(3.0, help="hair volume voxel size (mm)")) -> None:
    """Generate head scans from anny identities with hair styles and exact ground truth."""
    from headforge.craft.scans import ScanSetConfig, generate_scans

    try:
        cfg = ScanSetConfig(n=n, seed=seed, harder=harder, hair_voxel_m=voxel_mm / 1000)
        keys = generate_scans(output, cfg, log=typer.echo)
    except HeadforgeError as exc:
        _fail(exc)
    typer.echo(f"{len(keys)} scans in {output} (contact sheet: {output / 'contact_sheet.png'})")


@app.command("register")
def register(scans: Path = typer.Argument(..., help="folder of scans: generated scan folders or OBJ/PLY/GLB/STL files"),
             output: Path = typer.Option(..., "-o", "--output", help="folder for the maps and registrations"),
             preset: str = typer.Option("quick", help="quick (CPU) or paper"),
             map_size: int = typer.Option(256, help="displacement map size in texels"),
             units: str = typer.Option("auto", help="external scans: auto, m, cm, mm or metres per unit"),
             up: str = typer.Option("+y", help="external scans: the file's up axis (+x, -x, +y, ...)"),
             forward: str = typer.Option("+z", help="external scans: the axis the face looks along"),
             only: str | None = typer.Option(None, help="comma-separated scan names to register"),
             ablation: str = typer.Option("both", help="both, stage1, stage2 or stage1_weights2 (Fig. 10)"),
             steps_scale: float = typer.Option(1.0, help="multiply every optimisation step count (smoke runs)"),
             ray: bool = typer.Option(False, "--ray", help="run the scans as tasks on a local Ray runtime"),
             ray_address: str | None = typer.Option(None, "--ray-address", help="Ray cluster address (implies --ray)"),
             model: str = typer.Option("open-head", "--model", "-m", help="open-head or flame"),
             flame_dir: str | None = typer.Option(None, "--flame-dir", help="folder with FLAME's generic_model.pkl")) -> None:
    """Register a folder of scans (resumable; one bad scan never stops the rest)."""
    from headforge.batch import run_batch, summary_table
    from headforge.craft.pipeline import list_scans, register_item

    try:
        if map_size < 32 or map_size > 4096 or map_size & (map_size - 1):
            raise HeadforgeError(f"--map-size must be a power of two within 32-4096, got {map_size}")
        items = list_scans(scans)
        if only:
            wanted = set(only.split(","))
            items = [it for it in items if it[0] in wanted]
            if not items:
                raise HeadforgeError(f"none of {sorted(wanted)} is in {scans}")
        opts = dict(preset=preset, map_size=map_size, units=units, up=up, forward=forward, head_model=model,
                    flame_dir=flame_dir, ablation=ablation, steps_scale=steps_scale)
        from headforge.craft.pipeline import ItemOptions, config_for

        config_for(ItemOptions(**opts))  # bad preset/ablation: fail before any work
        result = run_batch([(k, {"path": p, **opts}) for k, p in items], register_item, output,
                           ray=ray, ray_address=ray_address, log=typer.echo)
    except HeadforgeError as exc:
        _fail(exc)
    typer.echo(summary_table(result, ["face_med_mm", "hair_med_mm", "s2r_med_mm", "edge_ratio", "lmk_mm", "roundtrip_mm"]))
    if not result.ok:
        typer.echo("error: no scan was registered", err=True)
        raise typer.Exit(1)
    typer.echo(f"{len(result.ok)} registered, {len(result.failed)} failed; maps in {output}")
