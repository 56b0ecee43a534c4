"""couch: capture, process and synthesise human-chair interactions.

The shared core: body model (:mod:`couch.body`), rotations (:mod:`couch.rotations`), rigid
geometry (:mod:`couch.geometry`), on-disk schemas (:mod:`couch.schema`), atomic writes and the
restricted unpickler. Stages live in ``couch.capture``, ``couch.sync``, ``couch.fitting``,
``couch.augment``, ``couch.synthesis`` and ``couch.tools``.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("couch")
except PackageNotFoundError:  # running from a source tree that was not installed
    __version__ = "0.0.0+unknown"


def __getattr__(name: str):
    # ``couch.process`` is the pipeline's entry point; it lives in a later stage, so it is
    # imported only when asked for (importing ``couch`` stays light and free of cycles).
    if name == "process":
        from couch.tools.process import process

        return process
    raise AttributeError(f"module 'couch' has no attribute {name!r}")
