"""`drivesim meshes`: the parametrizable vehicle mesh library (build, import, preview)."""
