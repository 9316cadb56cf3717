"""The one error type of `geoavatar prepare`: bad input, with a message naming the file or option."""

from geoavatar.errors import GeoAvatarError


class PrepareError(GeoAvatarError, RuntimeError):
    """Bad input to `geoavatar prepare` (unreadable video, no face, too few frames, missing files)."""


__all__ = ["PrepareError"]
