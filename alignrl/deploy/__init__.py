"""Deployment: a trained aligner as a self-contained policy file with its model card
(`export`, `card`), run on an instrument through the safety shield (`align`)."""

__all__ = ["card", "export"]
