"""Sinks of AnimationFrames (animation/frames.py's FrameSink): used inside `with`, fed by `write(frame, posed)`.

    mp4.py          Mp4Sink: each frame rendered (rasterize_gaussians on the posed avatar), optionally beside its
                    picture, into an mp4 (io/video.py's Mp4Writer)                            reenact, drive --out
    web.py          WebClip: posed vertices and head pose codes collected into the browser player's assets, written
                    as the player folder                                                     export --format web, view
    browser.py      LiveStream: each frame's posed mesh streamed to the browser player (LiveViewer, which also serves
                    view's sliders)                                                          drive --view
"""
