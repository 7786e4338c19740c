"""The three-laser-dot 6-DOF pose (Kara Mohamed, Patra and Lanzon; ../shared/seeds/
laser-dots-indoor-navigation.txt) on a downward camera.

Three laser pointers fixed to the body shoot at the floor; the downward camera sees their dots
and the floor's ArUco markers. The parts, each plain numpy/OpenCV with no I/O:

- :mod:`companion.laser_beams` (outside the package: the simulator draws the same rig): the beam
  rig (origins and directions in body FRD), nominal or calibrated;
- :mod:`.detect`: the dots in an image (red dominance, blobs, sub-pixel centroids, which beam
  made which dot);
- :mod:`.floor`: the floor markers in an image, the image-to-floor homography, the dots on the floor;
- :mod:`.geometry`: the pose from three floor dots (the seed's 90-degree closed form, Grunert
  P3P with solution selection, attitude from the beam matrices), the structured-light height and
  tilt without a marker, covariance from pixel noise, the field-of-view constraint;
- :mod:`.calibrate`: beam directions and origins from frames at known poses;
- :mod:`.pipeline`: the ``pipelines.laser_dots`` pipeline that ties them to the daemon.
"""
