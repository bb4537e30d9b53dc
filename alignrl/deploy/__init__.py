"""Deployment: a trained aligner as a self-contained policy file with its model card
(`export`: the job; `graph`, `formats`, `parity`, `card` its parts; `loading` runs the file),
run on an instrument through the safety shield (`align`)."""

__all__ = ["align", "card", "export", "formats", "graph", "loading", "parity", "policy"]
