"""One error root for everything auxgps raises on purpose.

The CLI turns any :class:`AuxGpsError` into one line on stderr and exit code 1; anything else is a bug.
"""


class AuxGpsError(Exception):
    """Root of every error auxgps raises for bad input or a failed precondition."""


class ConfigError(AuxGpsError):
    """A configuration or world file is missing, unreadable, or has a bad key or value."""


class CameraError(AuxGpsError):
    """A camera model is inconsistent (for example a non-positive focal length)."""


class FrameError(AuxGpsError):
    """An image frame cannot be used (wrong shape, wrong type, empty)."""


class MapError(AuxGpsError):
    """A landmark map file is missing, truncated, or of an unknown version."""


class PhotoError(AuxGpsError):
    """A photo or photo folder cannot be used (missing, not an image, truncated, no usable metadata)."""


class PhotoMapError(AuxGpsError):
    """A landmark map cannot be built from the photos given (too few geotagged, overlapping photos)."""


class LinkError(AuxGpsError):
    """The link to the autopilot cannot be opened (bad address, missing device, no permission, refused), or its
    reader stopped."""


class RecordingError(AuxGpsError):
    """A recording that cannot be read at all (a problem inside one is a line, not an error)."""
