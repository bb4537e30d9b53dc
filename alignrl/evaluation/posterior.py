"""A Bayesian autofocus that knows its columns' model: what a controller can do with
everything but the optimum (issue 21).

`BayesianAutofocus(family)` aligns the focus knob of a column drawn from `family`: the inference
of alignrl/posterior/inference.py (`FamilyPosterior`: a posterior over where the
optimum lies and which of the box's columns it is on, updated by every reading), written to
an apparatus. Each probe goes where the expected posterior variance of the optimum is
least; once the setting most likely to pass the session's verification passes with the
`confidence` asked, it writes that setting and leaves. Every setting is approached from
below, as the hyperbola fit does, so that the model's backlash is the same on every reading.

Given a single instrument's own file it is an oracle; given the training box
(`family_posterior`) it knows what training knows (`alignrl evaluate --policy posterior`,
and `posterior-scale-free` in any pixel scale). `python -m benchmarks.bound` runs both on
every instrument of a set.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from alignrl.apparatus.base import Apparatus
from alignrl.evaluation.controllers import approach_from_below, measure_width
from alignrl.posterior.inference import SCALE_FREE, FamilyPosterior
from alignrl.posterior.models import FAMILY_REACH, focus_box

__all__ = ["ROBUST", "BayesianAutofocus", "family_posterior"]

OVERSHOOT = 0.01  # share of the interval a setting below the present one is approached from


@dataclass
class BayesianAutofocus(FamilyPosterior):
    """The Bayesian autofocus of the module docstring, for columns of `family`."""

    def align(self, apparatus: Apparatus, knob: str, budget: int) -> None:
        low, high = (float(value) for value in apparatus.knobs[knob])
        width = high - low
        self.begin()
        for _ in range(min(budget, self.max_acquisitions)):
            probe, done = self.decide()
            if done:
                break
            self._write(apparatus, knob, low, width, probe)
            self.observe(probe, measure_width(apparatus))
        setting, _ = self.final()
        self._write(apparatus, knob, low, width, setting)

    def _write(self, apparatus: Apparatus, knob: str, low: float, width: float, u: float) -> None:
        high = float(apparatus.knobs[knob][1])  # low + 1.0 x width may round past it
        target = min(low + float(np.clip(u, 1e-6, 1.0)) * width, high)
        approach_from_below(apparatus, knob, target, OVERSHOOT * width)


# posterior-robust: the scale-free posterior for readings measured on images. Four times the
# columns (with 256 a few columns soon carry the weight, and the posterior is sure of a
# setting that a wider choice of curves would doubt: on val-steep, analytic, 60 alignments,
# seed 3,000,000, 48/60 at 5 acquisitions against 57/60 at 5 with 1024), and readings far
# from focus trusted less (images: 37/60 at 6; 1024 columns 44/60 at 6; and far_noise 0.1
# 51/60 at 7). Over set:validation (images, 100 per instrument, seed 3,000,000): 584/600 at
# 5 (docs/benchmarks.md, "Where the posterior is too sure").
ROBUST = {**SCALE_FREE, "draws": 1024, "far_noise": 0.1}


def family_posterior(
    reach: float = FAMILY_REACH, scale_free: bool = False, robust: bool = False
) -> BayesianAutofocus:
    """The posterior over the focus training box (alignrl/apparatus/families/focus.yaml),
    widened by `reach`: a Bayesian autofocus for a column of the focus family or near it,
    whatever its units (`alignrl evaluate --policy posterior`); `scale_free`, in any pixel
    scale too (`--policy posterior-scale-free`: one specimen point, the unknown factor covers
    the specimen's scale); `robust`, scale-free with ROBUST's columns and far_noise, for
    readings measured on images (`--policy posterior-robust`)."""
    box = focus_box(reach)
    if robust:
        return BayesianAutofocus(box, name="posterior-robust", **ROBUST)
    if scale_free:
        return BayesianAutofocus(box, name="posterior-scale-free", **SCALE_FREE)
    return BayesianAutofocus(box)
