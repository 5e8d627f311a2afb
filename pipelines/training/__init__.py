"""Training of every model from the preprocessed store: one loop (:mod:`.loop`), one task per stage
(:mod:`.detector`, :mod:`.segmenter`, :mod:`.baselines`) behind one interface (:mod:`.task`), and one
config class with one override rule (:mod:`.config`). The jobs are :mod:`pipelines.training.train` and
:mod:`pipelines.training.train_baselines`."""
