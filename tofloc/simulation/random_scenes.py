"""Random rooms: scenes drawn from a stated distribution, so that no estimator default can
have been tuned on them.

The scene library (``tofloc/simulation/scenarios/``) holds five hand-made rooms; a result
that holds there may still owe something to the rooms' choice. :func:`random_scene` draws
a room of its own from the distribution below (seeded, so ``(seed, index)`` always gives
the same room), as a scenario that ``extends = "paper"`` (the paper's robot and ToF physics)
and that :func:`tofloc.simulation.scenario.scenario_from_dict` validates like any file.
``tofloc scenes --random N`` runs N of them beside (or instead of) the library and writes
each one's TOML into ``OUT/random-scenes/``, to simulate or inspect again.

The distribution (every draw independent and uniform unless said):

* **Room**: a rectangle ``W x D`` with ``W, D`` in [2, 5] m, or with probability 0.4 an L
  (a corner rectangle of 30-60 % of each side cut away, at a random corner); ceiling at 2.2
  to 3.0 m; floor and ceiling closed.
* **Mapped boxes**: 0 to 4; footprint sides 0.2-0.8 m; with probability 0.5 floor to
  ceiling (a pillar), else 0.4-1.8 m high (furniture); inside the room.
* **Unmapped boxes** (objects the map does not hold): 0 to 2; sides 0.2-0.5 m, 0.3-1.2 m
  high.
* **Base**: height 1.0 to ``min(1.6, ceiling - 0.3)`` m, yaw in [-180, 180) deg, position
  anywhere the hanging robot clears the walls and every box by 0.3 m beyond its reach
  (:func:`tofloc.simulation.scenario.base_clearance_problem` with the reach so enlarged);
  boxes are redrawn (then dropped) when no such position is found in 200 draws.
* **Map**: a CAD mesh or a 20,000-point cloud (probability 0.5 each), faces off by 3 mm
  (``cad_error_sigma``).
* **Rig**: 3 sensors at 120 deg or 4 at 90 deg (probability 0.5 each) turned together by
  a random angle, tilted down 5 to 35 deg, 8x8 zones (probability 0.75) or 4x4; the
  perturbed variant's support rotation in [-3, 3] deg (the paper's declared 3 deg
  tolerance and mounting scatter, inherited).
* **Protocol**: 3 kPa pressure steps (126 postures), 2 motion-capture dropouts (as the
  library's rooms).
"""

from __future__ import annotations

import dataclasses
import numbers
from typing import Any

import numpy as np

__all__ = ["random_scene", "random_scene_name", "RANDOM_PREFIX", "MAX_RANDOM_SCENES"]

#: Names of random scenes: ``random-s<seed>-<index>`` (the seed in the name, so that a run
#: folder's scenes of two seeds never share a sub-folder).
RANDOM_PREFIX = "random"

#: At most this many random scenes per run.
MAX_RANDOM_SCENES = 100

#: Clearance (m) between the robot's reach and any wall or box, beyond what the simulator requires.
_MARGIN = 0.3
_BASE_DRAWS = 200
_LAYOUT_DRAWS = 20


def random_scene_name(seed: int, index: int) -> str:
    """The name of random scene ``index`` of ``seed``: ``random-s<seed>-<index, 2 digits>``."""
    return f"{RANDOM_PREFIX}-s{int(seed)}-{int(index):02d}"


def _outline(rng: np.random.Generator) -> tuple[list[list[float]], float, float]:
    W, D = (round(float(v), 3) for v in rng.uniform(2.0, 5.0, 2))
    rect = [[0.0, 0.0], [W, 0.0], [W, D], [0.0, D]]
    if rng.random() >= 0.4:
        return rect, W, D
    cw, cd = float(rng.uniform(0.3, 0.6)) * W, float(rng.uniform(0.3, 0.6)) * D
    corner = int(rng.integers(4))  # which corner is cut: the L's notch, counter-clockwise outline
    outlines = [
        [[cw, 0.0], [W, 0.0], [W, D], [0.0, D], [0.0, cd], [cw, cd]],  # at (0, 0)
        [[0.0, 0.0], [W - cw, 0.0], [W - cw, cd], [W, cd], [W, D], [0.0, D]],  # at (W, 0)
        [[0.0, 0.0], [W, 0.0], [W, D - cd], [W - cw, D - cd], [W - cw, D], [0.0, D]],  # at (W, D)
        [[0.0, 0.0], [W, 0.0], [W, D], [cw, D], [cw, D - cd], [0.0, D - cd]],  # at (0, D)
    ]
    return [[round(x, 4), round(y, 4)] for x, y in outlines[corner]], W, D


def _boxes(rng: np.random.Generator, env: Any, W: float, D: float, n: int, side: tuple[float, float],
           height: Any) -> list[list[float]]:
    from tofloc.simulation.world import box_problem

    out: list[list[float]] = []
    for _ in range(n):
        for _try in range(50):  # a footprint inside the room (an L's notch refuses some)
            sx, sy = (float(v) for v in rng.uniform(*side, 2))
            x0, y0 = float(rng.uniform(0.0, W - sx)), float(rng.uniform(0.0, D - sy))
            z1 = height(rng)
            box = [round(v, 4) for v in (x0, y0, 0.0, x0 + sx, y0 + sy, z1)]
            if box_problem(env, tuple(box)) is None:
                out.append(box)
                break
    return out


def random_scene(seed: int, index: int) -> dict[str, Any]:
    """Random scene ``index`` of ``seed`` as a scenario document (the dict a scenario TOML
    file parses to; the module's docstring gives the distribution).

    Parameters
    ----------
    seed, index : int
        ``>= 0``; the room is drawn from ``numpy.random.default_rng([seed, index])``.

    Returns
    -------
    dict
        ``{"scenario": ..., "environment": ..., "base": ..., ...}``, valid for
        :func:`tofloc.simulation.scenario.scenario_from_dict` (``extends = "paper"``).
    """
    from tofloc.simulation.scenario import Environment, base_clearance_problem, scenario_from_dict, scenario_sections

    if not all(isinstance(v, numbers.Integral) and not isinstance(v, bool) and v >= 0 for v in (seed, index)):
        raise ValueError(f"seed and index must be integers >= 0, got {seed!r} and {index!r}")
    rng = np.random.default_rng([int(seed), int(index)])
    name = random_scene_name(seed, index)
    outline, W, D = _outline(rng)
    z_max = round(float(rng.uniform(2.2, 3.0)), 3)
    env0 = Environment(kind="room", outline=tuple(map(tuple, outline)), z_min=0.0, z_max=z_max)
    n_mapped, n_unmapped = int(rng.integers(0, 5)), int(rng.integers(0, 3))
    n_sensors = 3 if rng.random() < 0.5 else 4
    azimuth0 = float(rng.uniform(0.0, 360.0 / n_sensors))
    rig = {"azimuths_deg": [round((azimuth0 + i * 360.0 / n_sensors) % 360.0, 3) for i in range(n_sensors)],
           "tilt_down_deg": round(float(rng.uniform(5.0, 35.0)), 2),
           "resolution": [8, 8] if rng.random() < 0.75 else [4, 4],
           "support_yaw_error_deg": round(float(rng.uniform(-3.0, 3.0)), 2)}
    map_kind = "mesh" if rng.random() < 0.5 else "cloud"
    yaw = round(float(rng.uniform(-180.0, 180.0)), 2)
    z_base = round(float(rng.uniform(1.0, min(1.6, z_max - 0.3))), 3)

    def document(boxes: list[list[float]], unmapped: list[list[float]], x: float, y: float) -> dict[str, Any]:
        env: dict[str, Any] = {"kind": "room", "outline": outline, "z_min": 0.0, "z_max": z_max, "floor": True,
                               "ceiling": True, "boxes": boxes, "unmapped_boxes": unmapped, "map_kind": map_kind,
                               "cad_error_sigma": 0.003}
        if map_kind == "cloud":
            env["map_points"] = 20000
        desc = (f"random room {index} of seed {seed}: {'L-shaped' if len(outline) == 6 else 'rectangular'} "
                f"{W:.2f} x {D:.2f} x {z_max:.2f} m, {len(boxes)} mapped and {len(unmapped)} unmapped boxes, "
                f"{n_sensors} VL53L5CX {rig['resolution'][0]}x{rig['resolution'][1]} tilted {rig['tilt_down_deg']:g} deg, "
                f"{'CAD mesh' if map_kind == 'mesh' else '20000-point cloud'} map")
        return {"scenario": {"extends": "paper", "name": name, "description": desc, "created": "2025-01-01T00:00:00+00:00"},
                "environment": env, "base": {"x": x, "y": y, "yaw_deg": yaw, "z": z_base},
                "protocol": {"pressure_step": 3.0}, "robot": {"mocap_dropouts": 2}, "rig": rig}

    for attempt in range(_LAYOUT_DRAWS + 1):
        last = attempt == _LAYOUT_DRAWS  # the last layout has no boxes: an empty room always has room
        boxes = [] if last else _boxes(rng, env0, W, D, n_mapped, (0.2, 0.8),
                                       lambda r: z_max if r.random() < 0.5 else round(float(r.uniform(0.4, 1.8)), 3))
        unmapped = [] if last else _boxes(rng, env0, W, D, n_unmapped, (0.2, 0.5), lambda r: round(float(r.uniform(0.3, 1.2)), 3))
        layout = scenario_sections(document(boxes, unmapped, W / 2, D / 2), f"<random scene {name}>")
        # the robot made longer by the margin: base_clearance_problem then asks for it beyond the reach
        wide = dataclasses.replace(layout, robot=dataclasses.replace(layout.robot, length=layout.robot.length + _MARGIN))
        for _ in range(_BASE_DRAWS):
            x, y = round(float(rng.uniform(0.0, W)), 4), round(float(rng.uniform(0.0, D)), 4)
            if base_clearance_problem(dataclasses.replace(wide, base=dataclasses.replace(wide.base, x=x, y=y))) is None:
                doc = document(boxes, unmapped, x, y)
                scenario_from_dict(doc, f"<random scene {name}>")  # every check of a scenario file
                return doc
    raise AssertionError("unreachable: an empty room of at least 2 x 2 m always has room for the base")
