"""Seeing what the robots did: episode pictures and GIFs (:mod:`ccrjax.viz.render`,
:mod:`ccrjax.viz.episode_pictures`), curves and search figures (:mod:`ccrjax.viz.plots`),
and the behavioural analysis of the hidden obstacle (:mod:`ccrjax.viz.analysis`)."""
