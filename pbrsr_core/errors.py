"""The project's typed errors.

Every failure a user can cause is one of these, with a message the user can act on. The API
maps ``http_status`` to its response, the CLI maps ``exit_code`` to its exit status, and a
worker stores ``str(error)`` as the job's error. Messages never contain tracebacks or server
paths (say "the file 'textures/a.png'" with the asset-relative name, not an absolute path).
"""

from __future__ import annotations


class PbrsrError(Exception):
    """Base class. ``code`` is a short machine-readable slug for problem bodies."""

    code = "error"
    http_status = 500
    exit_code = 1

    def __init__(self, message: str):
        super().__init__(message)
        self.message = message


class InvalidAsset(PbrsrError):
    """The bytes are not a readable asset: corrupt GLB, JSON that is not JSON, short buffers,
    accessors out of range, unresolvable or unsafe URIs, image bytes that do not decode."""

    code = "invalid-asset"
    http_status = 400
    exit_code = 3


class UnsupportedAsset(PbrsrError):
    """A kind of input pbrsr does not take (not glTF/GLB/zip, glTF 1.0, an image format
    OpenImageIO cannot read)."""

    code = "unsupported-asset"
    http_status = 415
    exit_code = 4


class LimitExceeded(PbrsrError):
    """Over a configured limit: upload size, triangles, texture dimensions, data URI size,
    uncompressed zip size."""

    code = "limit-exceeded"
    http_status = 413
    exit_code = 5


class UnprocessableAsset(PbrsrError):
    """A valid asset pbrsr cannot process as asked: no textures ("nothing to upscale"), no
    UVs with unwrapping turned off, an unsupported scale for the chosen prior, a referenced
    file the file system cannot open (a name too long for it, no permission)."""

    code = "unprocessable-asset"
    http_status = 422
    exit_code = 6


class InvalidOptions(PbrsrError):
    """Options that do not make sense (unknown preset or prior, bad scale)."""

    code = "invalid-options"
    http_status = 422
    exit_code = 2


class PriorUnavailable(PbrsrError):
    """A prior that is not installed here (weights not converted yet, optional package
    missing); the message names what to install."""

    code = "prior-unavailable"
    http_status = 422
    exit_code = 7


class StorageError(PbrsrError):
    """Writing results failed (disk full, permissions). Nothing partial is left behind."""

    code = "storage-error"
    http_status = 507
    exit_code = 8


class Cancelled(PbrsrError):
    """Raised by a progress callback to stop a run between iterations."""

    code = "cancelled"
    http_status = 409
    exit_code = 130
