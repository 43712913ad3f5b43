"""A run on disk and its numbers: the run folder (:mod:`ccrjax.run.folder`), checkpoints
(:mod:`ccrjax.run.checkpoint`), statistics over seeds (:mod:`ccrjax.run.stats`), the
hyperparameter selection rule (:mod:`experiments.selection`) and the paper's published
numbers (:mod:`experiments.paper`)."""
