"""The overhead camera's tracker: robots' poses, the boxes and the post-evaluation's start from a
video (``surprise-master track``; docs/tracking.md).

Modules:

* :mod:`tracking.config`: the tracking file (markers, floor, camera height) and the options;
* :mod:`tracking.camera`: the camera from the four corner markers, pixels to floor metres with
  the parallax of a marker above the floor;
* :mod:`tracking.boxes`: the boxes as blobs, and the start's paired with the end's for d_B;
* :mod:`tracking.tracker`: frames in, poses out (:class:`~tracking.tracker.Tracker`);
* :mod:`tracking.video`: a whole post-evaluation from a video or camera, and its files;
* :mod:`tracking.live`: the camera's view written for the dashboard while a run goes on.

OpenCV (the ``camera`` extra) is the laptop's, never a robot's.
"""
