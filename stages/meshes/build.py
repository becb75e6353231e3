"""Build the `meshes/` artifact: the procedural vehicles plus the imported user meshes, saved with trimesh."""

from __future__ import annotations

import time

from drivesim.pipeline.progress import progress_bar
from drivesim.pipeline.stage import BuildContext
from drivesim.sim.vehicle_library import VehicleModel, procedural_models, save_library
from drivesim.stages.meshes.config import MeshesConfig
from drivesim.stages.meshes.summary import MeshesSummary


def build_meshes(ctx: BuildContext) -> MeshesSummary:
    """Write every model's .ply files, materials.json and the library.json index into `ctx.dir`."""
    from drivesim.stages.meshes.import_mesh import import_vehicle

    cfg: MeshesConfig = ctx.config  # type: ignore[assignment]
    start = time.perf_counter()
    models: list[VehicleModel] = []
    sources: list[str] = []
    with progress_bar("vehicles", total=cfg.count + len(cfg.imports)) as (progress, task):
        for model in procedural_models(cfg.count, cfg.seed):
            models.append(model)
            sources.append("procedural")
            progress.advance(task)
        for imp in cfg.imports:
            models.append(import_vehicle(imp))
            sources.append(imp.path)
            progress.advance(task)
    names = [m.name for m in models]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        from drivesim.pipeline.errors import InputError

        raise InputError(f"two library models are named {duplicates[0]!r}: import it with --name NEW_NAME")
    if not models:
        from drivesim.pipeline.errors import InputError

        raise InputError("the library would be empty: use --count >= 1 or import a mesh")
    save_library(ctx.dir, models, sources)
    full = [sum(m.triangle_count for m in model.full) for model in models]
    light = [sum(m.triangle_count for m in model.light) for model in models]
    return MeshesSummary(
        model_count=len(models),
        imported_count=len(cfg.imports),
        full_triangles_mean=float(sum(full) / len(full)),
        light_triangles_mean=float(sum(light) / len(light)),
        seconds=time.perf_counter() - start,
    )
