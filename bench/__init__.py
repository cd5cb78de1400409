"""``steelscan bench``: accuracy and speed of each processing stage against baselines run
in the same process (:mod:`bench.run`; the sub-command: :mod:`bench.cli`)."""
