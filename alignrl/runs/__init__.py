"""Run directories and other policy sources: what a path or a name holds and how to read it.
`sources` decides what a spec names, once (`locate_source`: a league run, a training run, a
member or checkpoint file, an exported folder, a shipped champion) and loads its aligner
(`resolve_source`), as `export`, `align`, `evaluate`, `adapt` and league warm starts read
it; `training_runs` reads a training run's config and checkpoints (`member_spec`,
`load_policy`); `training_logs` writes its metrics CSVs and TensorBoard events; `report`
writes its report (`alignrl report`); `state` holds what every run keeps beside its weights.
Nothing here imports the league, deploy or the command line."""

__all__ = ["report", "sources", "training_logs", "training_runs"]
