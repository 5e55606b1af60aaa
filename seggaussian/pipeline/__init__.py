"""``seggaussian build``: raw scenes -> labelled Gaussians -> per-view label maps -> split-named Parquet shards.

``dataset.build_dataset`` is the entry point. ``discover`` finds the raw scenes, ``scene`` runs one scene through
the ``stages`` (each served from the ``cache`` when its key is unchanged), ``executors`` run scenes in this process,
a process pool or Ray (``ray_tasks``), ``slicing`` picks one slice of the scenes for a job array, ``assembly``
publishes the dataset's shards (then ``fragments`` points each scene's cache at its rows there), ``split`` assigns
train / val / xval, ``records`` holds what a build did, ``config`` its frozen configuration, ``export`` writes one
built scene as a labelled PLY. Nothing below this package (core, io, render, labels, fit, shards) imports it.
"""

__all__ = ["assembly", "cache", "config", "dataset", "discover", "executors", "export", "fragments", "ray_tasks",
           "records", "scene", "slicing", "split", "stages"]
