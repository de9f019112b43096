"""Navigation over a flight: the paper's whole loop (its Section II and Fig. 1), from frames to a track.

* :mod:`~mapdb.navigation.path` -- a flight's ground track: waypoints (a GeoJSON LineString, or a survey
  pattern over the densest part of a map) joined by turns of a given radius;
* :mod:`~mapdb.navigation.flight` -- a simulated flight: per frame the camera's objects (the simulator's
  detector model), the autopilot's sensors (time, attitude, barometric altitude, optionally an inertial
  velocity) and the truth;
* :mod:`~mapdb.navigation.velocity` -- velocity from frame to frame: the same objects matched image to
  image by a similarity (the matcher's own pieces), turned into metres per second;
* :mod:`~mapdb.navigation.bias` -- the frame-to-frame velocity's persistent error, measured against the
  applied fixes: it corrects the velocity and sizes the filter's drift allowance;
* :mod:`~mapdb.navigation.filter` -- the particle filter that fuses velocities and absolute fixes (with
  their runner-up candidates);
* :mod:`~mapdb.navigation.navigator` -- the loop: each frame's query uses the filter's prediction as its
  prior, the answer and the velocity update the filter;
* :mod:`~mapdb.navigation.track` -- the per-frame record, the GeoJSON track and the picture.

Library code only (no click): ``mapdb simulate flight`` and ``mapdb navigate`` are thin layers over it.
"""

__all__: list[str] = []
