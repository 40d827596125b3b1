"""The turntable's angle stream of a bag: ``sensor_msgs/JointState`` (radians; ``joint``
picks the name, or the one joint that holds and steps like a turntable) or
``std_msgs/Float64`` (radians, or degrees with ``angle_unit="deg"``), read in one pass over
that topic only (:func:`read_angles`). Used by ``lidarcal import`` (:mod:`lidarcal.io.bag`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..stationary import default_tolerance_deg, find_stationary, median_period_s
from .bag_read import FLOAT64, JOINTSTATE, Clock, connections
from .dataset import DatasetError


@dataclass
class AngleStream:
    t_s: np.ndarray  # sorted
    psi_deg: np.ndarray


def read_angles(reader, topic: str, joint: str | None, unit: str, bag: Path,
                clock: Clock) -> AngleStream:
    """All turntable readings of ``topic`` (one pass over that topic only), in degrees."""
    conns = connections(reader, topic)
    msgtype = conns[0].msgtype
    ts, ps = [], []
    idx: int | None = None
    several: dict[str, tuple[list[float], list[float]]] = {}  # joint -> (t, psi) to choose from
    seen: set[str] = set()
    for conn, log_ns, raw in reader.messages(connections=conns):
        msg = reader.deserialize(raw, conn.msgtype)
        if msgtype == FLOAT64:
            val = float(msg.data)
        else:
            names, pos = list(msg.name), np.asarray(msg.position, dtype=float)
            if joint is None:  # every joint by name (publishers may send different subsets)
                t = clock.time(topic, msg, log_ns)
                for nm, v in zip(names or [str(i) for i in range(len(pos))], pos.tolist()):
                    if math.isfinite(v):
                        several.setdefault(nm, ([], []))[0].append(t)
                        several[nm][1].append(math.degrees(v))
                continue
            if idx is None or idx >= len(names) or names[idx] != joint:
                seen.update(names)
                if joint not in names:  # another publisher's joints
                    continue
                idx = names.index(joint)
            if idx >= len(pos):
                continue
            val = float(pos[idx])
        if not math.isfinite(val):
            continue
        ts.append(clock.time(topic, msg, log_ns))
        ps.append(val if unit == "deg" and msgtype == FLOAT64 else math.degrees(val))
    if several and not ts:
        name = next(iter(several)) if len(several) == 1 else _turntable_joint(several, topic, bag)
        if len(several) > 1:
            clock.notes.append(f"{topic}: joint {name!r} is the turntable (the only joint of "
                               f"{', '.join(several)} that holds and steps); --joint names another")
        ts, ps = several[name]
    if joint is not None and msgtype == JOINTSTATE and not ts:
        raise DatasetError(bag, f"{topic}: no joint {joint!r} (--joint); its joints: "
                                f"{', '.join(sorted(seen)) or '(unnamed)'}")
    if len(ts) < 3:
        raise DatasetError(bag, f"{topic}: {len(ts)} usable angle reading(s); need a turntable "
                                "angle stream (--angle-topic, --joint)")
    t, p = np.asarray(ts), np.asarray(ps)
    order = np.argsort(t, kind="stable")
    return AngleStream(t[order], p[order])


def _turntable_joint(joints: dict[str, tuple[list[float], list[float]]], topic: str,
                     bag: Path) -> str:
    """The joint that moves like a turntable: its readings hold still at three or more
    distinct angles (:func:`lidarcal.stationary.find_stationary` with the default tolerance
    and three reading periods). Exactly one such joint, or an error listing them all."""
    steps = {}
    for name, (t, p) in joints.items():
        t_a, p_a = np.asarray(t), np.asarray(p)
        order = np.argsort(t_a, kind="stable")
        t_a, p_a = t_a[order], p_a[order]
        if t_a.size < 3:
            steps[name] = 0
            continue
        tol = default_tolerance_deg(p_a)
        periods = find_stationary(t_a, p_a, tol, 3.0 * median_period_s(t_a))
        steps[name] = len({round(q.psi_deg / (2.0 * tol)) for q in periods})
    stepping = [n for n, k in steps.items() if k >= 3]
    if len(stepping) == 1:
        return stepping[0]
    seen = ", ".join(f"{n} ({k} still angle{'s' if k != 1 else ''})" for n, k in steps.items())
    raise DatasetError(bag, f"{topic} has {len(joints)} joints ({seen}) and "
                            f"{'none' if not stepping else len(stepping)} of them steps like a "
                            "turntable; name the turntable with --joint")
