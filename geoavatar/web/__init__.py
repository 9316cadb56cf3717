"""The browser player: its built page and script (static/, made by `make web` from the repo's web/ folder) and
what feeds it, an avatar + clip in the player's format (pack.py) and a live stream of posed meshes (live.py)."""

from geoavatar.web.pack import PlayerAssets, player_assets, write_player_folder

__all__ = ["PlayerAssets", "player_assets", "write_player_folder"]
