"""`drivesim meshes`: the vehicle library (build, import, preview)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from drivesim.cli.common import ConfigOption, ForceOption, console, said_fresh, set_option, workspace
from drivesim.pipeline.config import load_config

meshes_app = typer.Typer(no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False)

AXES = ("auto", "+x", "-x", "+y", "-y", "+z", "-z")


def _print_result(result) -> None:
    if said_fresh(result, "meshes", plural=True):
        return
    s = result.summary
    console.print(
        f"[green]meshes[/] {s.model_count} vehicles ({s.imported_count} imported), "
        f"{s.full_triangles_mean:.0f} / {s.light_triangles_mean:.0f} triangles full / light on average "
        f"-> {result.path} (look at them: drivesim meshes preview)",
        highlight=False,
        soft_wrap=True,
    )


@meshes_app.command("build")
def build_command(
    count: Annotated[
        int | None, typer.Option("--count", help="Procedural vehicles (body types in turn; config: count).")
    ] = None,
    seed: Annotated[int | None, typer.Option("--seed", help="Seed of shapes and paints (config: seed).")] = None,
    config: ConfigOption = None,
    set_: set_option("count=12") = None,
    force: ForceOption = False,
) -> None:
    """Build <workspace>/meshes/: procedural vehicles plus the meshes imported before.

    Sedans, hatchbacks, SUVs, vans and pickups (closed meshes, body / windows / wheels / lights, full and light
    detail), as .ply + materials.json.
    """
    from drivesim.stages.meshes.config import ImportConfig, MeshesConfig
    from drivesim.stages.meshes.stage import current_imports, run_meshes

    ws = workspace()
    overrides = list(set_ or [])
    overrides += [f"count={count}"] if count is not None else []
    overrides += [f"seed={seed}"] if seed is not None else []
    cfg = load_config(MeshesConfig, preset="meshes", config_file=config, overrides=overrides)
    if not cfg.imports:  # a rebuild keeps what was imported
        cfg = cfg.model_copy(update={"imports": [ImportConfig.model_validate(i) for i in current_imports(ws)]})
    _print_result(run_meshes(ws, cfg, force=force))


@meshes_app.command("import")
def import_command(
    file: Annotated[
        Path, typer.Argument(help="The vehicle mesh: .obj, .glb, .gltf, .ply or .stl.", show_default=False)
    ],
    up: Annotated[
        str, typer.Option("--up", help="The file's up axis; auto: +y for .obj/.glb/.gltf (glTF), +z for .ply/.stl.")
    ] = "auto",
    forward: Annotated[
        str,
        typer.Option("--forward", help="Axis the car's front points along; auto: +z for .obj/.glb/.gltf, else +x."),
    ] = "auto",
    length_m: Annotated[
        float | None,
        typer.Option(
            "--length-m",
            help="Real bumper-to-bumper length in metres (default: the file's size read as m, cm or mm).",
            show_default=False,
        ),
    ] = None,
    name: Annotated[
        str | None, typer.Option("--name", help="Name in the library (default: the file's stem).", show_default=False)
    ] = None,
) -> None:
    """Add a user's car to <workspace>/meshes/ at its real size.

    The mesh is turned into the vehicle frame (x forward, z up, origin at the footprint centre on the ground); the
    library is rebuilt atomically with it.
    """
    from drivesim.pipeline.errors import InputError
    from drivesim.stages.meshes.config import ImportConfig, MeshesConfig
    from drivesim.stages.meshes.import_mesh import import_vehicle
    from drivesim.stages.meshes.stage import current_imports, run_meshes

    if up not in AXES or forward not in AXES:
        raise InputError(f"--up and --forward take one of {', '.join(AXES)}")
    ws = workspace()
    if length_m is not None and not 0.5 < length_m <= 25.0:
        raise InputError(f"--length-m {length_m:g} is no vehicle length: give the real length in metres (0.5-25)")
    imp = ImportConfig(path=str(file.absolute()), name=name, up_axis=up, forward_axis=forward, length_m=length_m)
    model = import_vehicle(imp)  # bad input fails here, before the artifact is touched
    with ws.lock("meshes"):  # read, add, rebuild as one: two imports at once never lose one of them
        manifest = ws.read_manifest("meshes") or {}
        base = manifest.get("config") or load_config(MeshesConfig, preset="meshes").model_dump(mode="json")
        others = [i for i in current_imports(ws) if Path(i["path"]) != file.absolute()]
        cfg = MeshesConfig.model_validate({**base, "imports": [*others, imp.model_dump(mode="json")]})
        result = run_meshes(ws, cfg, force=True)
    console.print(
        f"imported {model.name}: {model.length_m:.2f} x {model.width_m:.2f} x {model.height_m:.2f} m, "
        f"{sum(m.triangle_count for m in model.full)} / {sum(m.triangle_count for m in model.light)} triangles "
        "full / light",
        highlight=False,
        soft_wrap=True,
    )
    _print_result(result)


@meshes_app.command("preview")
def preview_command(
    out: Annotated[
        Path | None,
        typer.Option("--out", "-o", help="PNG to write (default <workspace>/meshes-preview.png).", show_default=False),
    ] = None,
    detail: Annotated[str, typer.Option("--detail", help="Level of detail to draw: full or light.")] = "full",
) -> None:
    """Render a lit contact sheet of the workspace's vehicle library.

    The procedural default when the workspace has none; drawn with the simulator's rasterizer.
    """
    from drivesim.pipeline.errors import InputError
    from drivesim.sim.vehicle_library import VehicleLibrary
    from drivesim.stages.meshes.preview import contact_sheet

    if detail not in ("full", "light"):
        raise InputError("--detail takes full or light")
    ws = workspace()
    root = ws.artifact_dir("meshes")
    if (root / "library.json").is_file():
        try:
            library = VehicleLibrary.load(root)
        except (ValueError, FileNotFoundError) as exc:
            raise InputError(f"{exc}; rebuild it with drivesim meshes build --force") from None
        source = str(root)
    else:
        library, source = VehicleLibrary.procedural(), "the procedural default (no meshes/ in the workspace)"
    path = contact_sheet(library, out or ws.root / "meshes-preview.png", detail=detail)
    console.print(
        f"[green]preview[/] {len(library.models)} vehicles of {source} -> {path}", highlight=False, soft_wrap=True
    )
