"""Run directories: what a run holds and how to read it. `sources` names the trained aligner a
run, a member file or a training checkpoint stands for (`resolve_source`), as `export`,
`align`, `adapt` and league warm starts read it; `training_runs` reads a training run's
config and checkpoints (`member_spec`, `load_policy`)."""

__all__ = ["sources", "training_runs"]
