"""The chain of stages: its registry (`registry.py`: every stage's `StageSpec`, in order), its walker (`run.py`:
`drivesim run`, each stage skipped when fresh), the procedural towns (`towns.py`: small chains of their own that
make extra worlds to train on) and a run's further recordings (`recordings.py`: a world each, in `drives/<name>/`).

The chain sits above the stages: it imports their specs and runners, no stage imports it.
"""
