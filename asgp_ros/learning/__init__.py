"""The offline learning side: from recordings to trained models, scores and the paper's tables.

* :mod:`asgp_ros.learning.dataset` -- the paper's recordings, simulated in its layout
  (``asgp dataset``);
* :mod:`asgp_ros.learning.training` -- bags to a model file, with the ASGP's automatic
  configuration and variance calibration (``asgp train``);
* :mod:`asgp_ros.learning.evaluation` -- k-step path-prediction scores as in the paper, and
  an adapting model scored causally (``asgp evaluate``);
* :mod:`asgp_ros.learning.reproduce` -- the paper's protocol end to end (``asgp reproduce``)
  beside :mod:`asgp_ros.learning.paper`, the paper's published Tables I-III.

ROS-free: it reads bags through :mod:`asgp_ros.recording` and fits and predicts with
:mod:`asgp_ros.core`; no node imports it. Nothing is imported here, so that a command loads
only the modules it uses.
"""
