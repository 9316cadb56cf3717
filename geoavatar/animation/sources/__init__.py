"""Sources of AnimationFrames (animation/frames.py's FrameSource): each has `fps`, `live`, `audio` and `close()`.

    split.py         SplitFrames: a run's own frames (RunFrames' parameters, T rule)   export --format web, view
    driver.py        DrivenAvatar: a tracked driver dataset, transferred, with its     reenact, eval --driver
                     pictures; DriverMotion: its motion alone, one frame a timestep    export --format web --driver
    driver_video.py  a driver video tracked into a driver dataset by prepare's pipeline (RUN/drivers/, reused)
    live.py          LiveDriver: a camera or a video tracked live (capture.py: the     drive
                     input and the mailboxes between the threads; tracker.py: the
                     identity stage and the online fit)
"""
