"""The one error type of `geoavatar prepare`: bad input, with a message naming the file or option."""


class PrepareError(RuntimeError):
    """Bad input to `geoavatar prepare` (unreadable video, no face, too few frames, missing files)."""


__all__ = ["PrepareError"]
