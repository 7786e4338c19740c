"""Writes the outdoor world of the EKF-SLAM return to base (config/worlds/outdoor.yaml).

``python -m sitl.outdoor_world > config/worlds/outdoor.yaml``: the landmark field of the seed's
simulations (sitl/slam_experiment.py ``make_world``: one point landmark per 1000 m^2 over
[-150, 650] m squared, 0-5 m high) drawn once with :data:`SEED`, the base at the seed's (353.5,
353.5) m and the take-off there: a flight out to the jam point at the origin, 500 m away, and
back. The base is marked as well: a landmark on the ground at the base (the landing pad's marker,
as precision landing uses one), the last id. With one field landmark per 1000 m^2, a landing from
the held altitude without it descends blind for its last ~50 m (the sensor's footprint holds no
landmark there) and drifts with the wind. LOCAL_NED metres (x north, y east).
"""

from __future__ import annotations

import sys

import numpy as np
import yaml

from sitl.slam_experiment import AREA_NE, BASE_NE, make_world

SEED = 14
MARKER_SIZE_M = 4.0  # black square's side: 59 px across from 60 m through a 40-degree 640 px camera
MARKER_DICTIONARY = "DICT_4X4_1000"  # 641 landmarks need more ids than the simulator's default DICT_4X4_250
MARKER_MARGIN_M = 5.0


def outdoor_world() -> dict:
    """The world document (companion/world.py)."""
    field_marks = make_world(np.random.default_rng(SEED)).landmarks
    landmarks = np.vstack([field_marks, [[BASE_NE[0], BASE_NE[1], 0.0]]])  # the landing pad's marker last
    (n0, n1), (e0, e1) = AREA_NE
    return {
        "name": "outdoor-field",
        "wall_angle_deg": 90,
        "bounds": {"min": [n0, e0], "max": [n1, e1]},
        "start": [BASE_NE[0], BASE_NE[1], 225.0],
        "base": list(BASE_NE),
        "landmarks": [{"id": k, "position": [round(float(p[0]), 2), round(float(p[1]), 2)],
                       "height_m": round(float(-p[2]), 2) + 0.0} for k, p in enumerate(landmarks)],
    }


def outdoor_markers_world() -> dict:
    """The world document of the camera path: :func:`outdoor_world` with a floor marker at every
    landmark (module docstring)."""
    world = outdoor_world()
    (n0, e0), (n1, e1) = world["bounds"]["min"], world["bounds"]["max"]
    m = MARKER_MARGIN_M
    landmarks = [{**mark, "height_m": 0.0} for mark in world["landmarks"]]
    return {**world, "name": "outdoor-field-markers",
            "bounds": {"min": [n0 - m, e0 - m], "max": [n1 + m, e1 + m]},
            "landmarks": landmarks,
            "marker_dictionary": MARKER_DICTIONARY,
            "floor_markers": [{"id": mark["id"], "position": list(mark["position"]), "size_m": MARKER_SIZE_M}
                              for mark in landmarks]}


def main(argv: list[str] | None = None) -> None:
    markers = "--markers" in (sys.argv[1:] if argv is None else argv)
    if markers:
        sys.stdout.write("# The outdoor landmark field of the EKF-SLAM return to base on the camera path (a floor\n"
                         "# marker at every landmark): written by\n"
                         "# python -m sitl.outdoor_world --markers > config/worlds/outdoor-markers.yaml (see that module).\n")
    else:
        sys.stdout.write("# The outdoor landmark field of the EKF-SLAM return to base: written by\n"
                         "# python -m sitl.outdoor_world > config/worlds/outdoor.yaml (see that module).\n")
    world = outdoor_markers_world() if markers else outdoor_world()
    yaml.safe_dump(world, sys.stdout, sort_keys=False, default_flow_style=None, width=120)


if __name__ == "__main__":
    main()
