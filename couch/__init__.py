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
