"""``ovgaussian view``: open-vocabulary queries of a Gaussian scene in the browser.

One concept per module:

- ``relevancy``: the calibrated relevancy (against the vocabulary and canonical negatives), LERF's, query parsing,
  highlight colours (pure numpy);
- ``calibration``: each vocabulary name's relevancy offset, fitted on the run's train rooms and cached in the run;
- ``cameras``: the scene's cameras as viewer poses, the camera the viewer opens at, the pose inside a bare splat;
- ``field``: the run's per-Gaussian language vectors, decoded once, with per-text score columns cached;
- ``scene``: the scene shown (splat file and/or dataset scene with ground truth), splat arrays, click picking;
- ``state``: colours and legend of every mode, query answers, what a clicked Gaussian is (no browser);
- ``app``: the viser server and GUI (imports viser, the ``view`` extra);
- ``config`` and ``session``: ``ViewConfig`` and ``run_view``, the command as one library call.
"""

__all__ = ["app", "calibration", "cameras", "config", "field", "relevancy", "scene", "session", "state"]
