"""The library's one error tree.

Every error probegrid raises on purpose for bad input or a failed job is a :class:`ProbegridError`,
with a one-line message naming what is wrong. Each keeps the builtin base it always had, so code
that catches ``ValueError`` or ``RuntimeError`` keeps working::

    Exception
     └── ProbegridError                         probegrid.errors (catch this for "any probegrid error")
          ├── SceneError(ValueError)            a scene cannot be used (file, glTF, geometry)
          ├── StoreError(ValueError)            a grid store cannot be read, written or resumed
          ├── ImageError(ValueError)            an image cannot be read or written
          ├── SettingsError(ValueError)         an option's value its settings refuse
          ├── ExecutorError(RuntimeError)       a batch failed, a worker died, no cluster
          ├── NoLightError(ValueError)          probegrid.bake.nolight: a bake that can only be black
          ├── KTX2Error(ValueError)             probegrid.export.ktx2: a KTX2 file or level refused
          └── ProbeGridError                    probegrid.client: every error of the HTTP client
               ├── InvalidArgumentError(ValueError)   bad arguments, caught before any request
               ├── ProbeGridResponseError             a body that is not the API's
               ├── ProbeGridConnectionError           the service cannot be reached
               ├── ProbeGridTimeoutError              an operation took longer than ``timeout``
               └── ProbeGridHTTPError                 a 4xx/5xx answer (status, code, message)
                    ├── BadRequestError               400 and 422
                    ├── NotFoundError                 404
                    └── ServerError                   5xx

Bad arguments to the pure functions of :mod:`probegrid.core` stay plain ``ValueError`` /
``TypeError`` with a full sentence (numpy's and trimesh's habit): they are programming errors of
the caller, not failures of a job.
"""

from __future__ import annotations

__all__ = ["ExecutorError", "ImageError", "ProbegridError", "SceneError", "SettingsError",
           "StoreError"]


class ProbegridError(Exception):
    """Base of every error probegrid raises for bad input or a failed job (one-line message)."""


class SceneError(ProbegridError, ValueError):
    """A scene that cannot be used (missing or broken file, bad geometry); one-line message."""


class StoreError(ProbegridError, ValueError):
    """A grid store cannot be read, written or resumed (one-line message)."""

    def __init__(self, message: str) -> None:
        super().__init__(" ".join(str(message).split()))


class ImageError(ProbegridError, ValueError):
    """An image file cannot be read or written; the message is one line naming the file."""


class SettingsError(ProbegridError, ValueError):
    """An option's value that a settings object refuses (its type or bounds); ``option`` names
    the field, ``reason`` says what is wrong, and the message is ``"<option>: <reason>"``."""

    def __init__(self, option: str, reason: str) -> None:
        super().__init__(f"{option}: {reason}")
        self.option = option
        self.reason = reason


class ExecutorError(ProbegridError, RuntimeError):
    """A batch failed, a worker died, or the cluster cannot be reached (one-line message)."""

    def __init__(self, message: str) -> None:
        super().__init__(" ".join(str(message).split()))
