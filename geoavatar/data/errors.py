"""The one exception of the data layer.

Every problem with a user's dataset (a missing file, an array of the wrong shape, inconsistent
frame counts, a head model that is not available) raises `DatasetError` with a message that names
the file and says what is wrong, so the CLI can print it without a traceback.
"""

from __future__ import annotations

from geoavatar.errors import GeoAvatarError


class DatasetError(GeoAvatarError, ValueError):
    """A dataset on disk is missing something or is inconsistent; the message names the file."""


__all__ = ["DatasetError"]
