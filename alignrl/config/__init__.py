"""Typed experiment configs, loaded strictly from YAML (experiments/*.yaml), one module a
concept:

    alignrl.config.learner       LearnerConfig: the `learner:` section, from the learners' registry
    alignrl.config.task_options  TaskOptions, ActingOptions: changes to a named task
    alignrl.config.run           RunConfig: what every run names (apparatus, task, history, ...)
    alignrl.config.adaptation    AdaptationConfig: where an adaptation came from, its shield
    alignrl.config.experiment    ExperimentConfig, load_experiment: a training experiment

How a config file is read (bounded YAML, overlays, `--set`, strict models) is
alignrl/config_reading.py's; a league's models are alignrl/league/config.py's. Import each
name from its module.
"""
