"""``ovgaussian view``: open-vocabulary queries of a Gaussian scene in the browser.

One concept per module:

- ``relevancy``: LERF relevancy against canonical negatives, query parsing, highlight colours (pure numpy);
- ``field``: the run's per-Gaussian language vectors, decoded once, with per-text score columns cached;
- ``scene``: the scene shown (splat file and/or dataset scene with ground truth), splat arrays, click picking;
- ``state``: colours and legend of every mode, query answers, what a clicked Gaussian is (no browser);
- ``app``: the viser server and GUI (imports viser, the ``view`` extra);
- ``config`` and ``session``: ``ViewConfig`` and ``run_view``, the command as one library call.
"""

__all__ = ["app", "config", "field", "relevancy", "scene", "session", "state"]
