"""ANIMATION layer: where per-frame head parameters come from (sources) and where the posed avatar goes (sinks),
between the commands (apps) and the layers they use (eval, train, prep, web and below).

    source = DrivenAvatar(run, driver, DrivingOptions(...))        # sources/: a run's split, a driver, the live tracker
    sinks = [Mp4Sink(run, out, source.fps, driven.fixed_camera)]   # sinks/: an mp4, the web player's clip, the browser
    play(run, source, sinks, progress=True)                         # play.py: each frame posed once, into every sink

frames.py       AnimationFrame (index, params, T, camera, picture, timestep, available, timings, record) and the
                FrameSource / FrameSink interfaces
posing.py       the one posing path (render_params, posed_head_vertices, browser_pose_code, record_camera, ...) and
                PosedFrame (a frame posed once for every sink)
transfer.py     driven_params: a driver's parameters become the avatar's (expression_transfer.py: the statistics and
                subspace modes)
play.py         play(run, source, sinks): the loop; for a live source drive's output stage (stats.py: DriveStats, the
                status line)

A source may carry a sound track (`audio`, None for every source so far) that the front end hands to the sinks (Mp4Sink
and WebClip take `audio=`).
"""
