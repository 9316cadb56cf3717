"""Data layer: read and write tracked subjects, split them, serve them as a torch Dataset.

    subject = open_subject("data/wojtek")          # VHAP / GaussianAvatars layout or INSTA, detected
    train = HeadAvatarDataset(subject, "train", DataConfig(resolution=256))

Readers: `layout.read_layout` (VHAP / GaussianAvatars + geoavatar.json), `insta.read_insta`
(metrical-tracker `.frame` files). Writer: `layout.LayoutWriter` (frame by frame, atomic).
Splits: `splits.split_timesteps` (INSTA protocol: the last 350 frames are the test set).
Every data problem raises `DatasetError`, whose message names the file.
"""

from geoavatar.data.dataset import DataConfig, HeadAvatarDataset, check_head_model, open_dataset, open_subject
from geoavatar.data.errors import DatasetError
from geoavatar.data.insta import read_insta
from geoavatar.data.layout import LayoutWriter, read_layout
from geoavatar.data.splits import ShortVideoWarning, Split, SplitConfig, evenly_spaced, split_timesteps
from geoavatar.data.subject import FrameRecord, Subject, SubjectInfo

__all__ = [
    "DataConfig", "DatasetError", "FrameRecord", "HeadAvatarDataset", "LayoutWriter", "ShortVideoWarning", "Split",
    "SplitConfig", "Subject", "SubjectInfo", "check_head_model", "evenly_spaced", "open_dataset", "open_subject",
    "read_insta",
    "read_layout", "split_timesteps",
]
