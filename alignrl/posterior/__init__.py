"""Inference about a column from its readings (design.md, "Layout"): between the apparatus
and the envs.

* models.py: the column models of a focus family (`ColumnModels`, `focus_box`);
* inference.py: the Bayesian posterior over the optimum and the column (`FamilyPosterior`);
* scale_sums.py: the readings' unknown pixel scale, marginalised in closed form;
* scoring.py: what the posterior's states would read, for its probe and its stop;
* workspace.py: what is made once per process, and the buffers each step reuses;
* calibration.py: the search for one column's model from its alignments (`calibrate`);
* hindsight.py: where an episode's optimum lay, told after it ended (`PooledCurve`), the
  critics' secret on a real column.

Who asks it: the Bayesian autofocus (alignrl/evaluation/posterior.py), an episode's end
(alignrl/envs/ending.py), `alignrl calibrate` (alignrl/deploy/calibrate.py) and the
critics' hindsight (alignrl/envs/hindsight.py). docs/posterior.md explains it.
"""
