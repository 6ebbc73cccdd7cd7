"""Exception types of torch-frontend."""

from __future__ import annotations


class ConfigError(ValueError):
    """A VINS config or camodocal camera file is missing, unreadable or malformed.

    The message names the file, the key (where one is at fault) and what was expected.
    """

    def __init__(self, message: str, path=None, key=None):
        self.path = None if path is None else str(path)
        self.key = key
        where = []
        if self.path:
            where.append(f"{self.path}")
        if key:
            where.append(f"key '{key}'")
        prefix = ": ".join(where)
        super().__init__(f"{prefix}: {message}" if prefix else message)


class ConfigWarning(UserWarning):
    """A config file has a key that nothing reads: a near-miss of a known key (``equalise``, "did
    you mean ``equalize``?") or a key that neither VINS nor torch-frontend reads. The key is
    ignored, as VINS would ignore it (``torch_frontend.config.KNOWN_KEYS``)."""


class DataWarning(UserWarning):
    """A note about input data that is used, but not as given: colour frames converted to grey
    (once per sequence). The CLI prints it as one ``torch-frontend: note: ...`` line."""


class WorldFrameWarning(UserWarning):
    """Loop closure's world frame looks wrong: poses whose motion is far from horizontal in the
    assumed up axis (the 4-DoF pose graph's yaw axis, the plots' viewing axis), naming the likely
    up axis (``torch_frontend.loop.world``). The CLI prints it as one ``torch-frontend: warning:``
    line."""


class DataError(ValueError):
    """Input data is missing, unreadable or inconsistent (a user error, not a bug).

    The message says what is wrong and where (file, folder, bag, topic); the CLI prints it as one
    line and exits with a non-zero code.
    """


class BadFrameError(DataError):
    """A frame that cannot be read (a missing, truncated or corrupt image file, an undecodable
    message) stopped a run. The readers skip such frames with ``skip_bad=True`` (the pipelines'
    ``skip_bad_frames``, the CLI's ``--skip-bad-frames``), and the message says so, naming the
    option of the layer that raised it (:meth:`naming`)."""

    @classmethod
    def naming(cls, message: str, option: str) -> BadFrameError:
        """``message`` and the option that skips such frames, in the library's style (backticks:
        a front end puts its own spelling in its place): "... (`skip_bad` skips unreadable frames)"."""
        return cls(f"{message} (`{option}` skips unreadable frames)")
