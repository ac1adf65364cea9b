"""The paper's experiment end to end (``asgp reproduce``): Tables I-III, plots and a report.

Protocol (Fan et al., ICRA 2018, Sec. V), on a dataset laid out by ``asgp dataset``
(DIR/{tile,carpet,hybrid}/<bag>, 8 / 8 / 2 bags):

* train sets: Tile = 6 tile bags, Carpet = 6 carpet bags, Both = 3 tile + 3 carpet;
* test sets: Tile = the 2 other tile bags, Carpet = the 2 other carpet bags, Hybrid = the
  2 hybrid bags;
* models: "ASGP (paper)", exactly the paper's configuration (s = 4, M = 20 / 40, one
  joystick axis and one velocity per channel: ``training.PAPER_OPTIONS``); "ASGP", the
  configuration ``asgp train`` chooses itself from the training bags
  (``training.train_auto``: lags, coupling and M by held-out k-step success, with its
  variance calibration); then every other trainable kind of the registry
  (:mod:`asgp_ros.core.models`): the paper's MLP (s = 10) and two simple baselines
  (constant velocity, first-order lag);
* horizons 1.0, 1.4, 2.0 s (k = 5, 7, 10 at 5 Hz), success = position error <= 10 cm.

The held-out bags are those the dataset's manifest marks "test" (``asgp dataset``: bags
7-8 of each surface); without a manifest, the last two of each surface sorted by name (the
paper does not say which of its recordings it held out). All models are trained first;
then all are scored on the SAME test steps: a step is a case when the largest s of the
trained models (at least the MLP's 10; the automatic ASGP may choose more) and k future
samples fit in one valid segment; each model uses its own last s of those.

Tables: Table I = tested on Tile, II = tested on Carpet, III = tested on Hybrid; rows =
train set x model, columns = horizons. Beside each of our cells of a model the paper ran
(its ASGP and MLP), the 'paper' column gives the paper's published figure for the same
test set, train set and horizon (:mod:`asgp_ros.learning.paper`; the paper's tables are one
per horizon, ours one per test set). Our data are simulated; the paper's come from a real
chair.

The modules, in the order a run uses them:

* :mod:`~asgp_ros.learning.reproduce.protocol` -- what is compared: the models, the train
  and test sets, the run's budgets, the targets;
* :mod:`~asgp_ros.learning.reproduce.data` -- the dataset on disk: its bags, its manifest,
  the paper's split, the small dataset of ``--quick``;
* :mod:`~asgp_ros.learning.reproduce.jobs` -- reading a bag, training a model, evaluating
  it, the propagation check; run by :mod:`~asgp_ros.learning.reproduce.pool`, a pool of
  worker processes sharing one read-only context;
* :mod:`~asgp_ros.learning.reproduce.tables`, :mod:`~asgp_ros.learning.reproduce.claims`
  and :mod:`~asgp_ros.learning.reproduce.summary` -- Tables I-III, the claims checked on
  our numbers, and ``results.json`` assembled from them;
* :mod:`~asgp_ros.learning.reproduce.report` and :mod:`~asgp_ros.learning.reproduce.plots`
  -- ``report.md`` and the figures;
* :mod:`~asgp_ros.learning.reproduce.run` -- :func:`~asgp_ros.learning.reproduce.run.run`,
  the steps in order, writing the report directory atomically.

Nothing is imported here.
"""
