"""Worker processes that end with the process that started them.

A ``ProcessPoolExecutor`` whose parent is killed (SIGKILL, an out-of-memory kill, a closed terminal) leaves its
workers running their current task to the end: a CPU fit or a training that nobody waits for, holding the cores. Every
pool of the toolkit starts its workers with :func:`exit_with_parent`, so they go within ``PARENT_POLL_SECONDS``.
"""

from __future__ import annotations

import os
import threading
import time

#: How often (s) a worker checks that the process that started it is still there.
PARENT_POLL_SECONDS = 1.0


def exit_with_parent(parent: int) -> None:
    """Pool initializer (``initializer=exit_with_parent, initargs=(os.getpid(),)``): a daemon thread that ends this
    process once ``parent`` is gone (it is then no longer this process's parent)."""

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_POLL_SECONDS)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def pool_options(context) -> dict:
    """The keyword arguments of a ``ProcessPoolExecutor`` of ``context`` whose workers end with this process."""
    return dict(mp_context=context, initializer=exit_with_parent, initargs=(os.getpid(),))
