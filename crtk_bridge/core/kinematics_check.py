"""Validate a profile's ``kinematics`` sections against their URDFs, naming the profile key.

The kinematics itself (:class:`~crtk_bridge.core.kinematics.Kinematics`) names the URDF and what
is missing from it; a user edits the profile, so here every error names the profile's key too
(``namespaces[0] (so101).kinematics.tip_frame``). Used by ``crtk-bridge check`` and by the daemon
before it starts anything.
"""

from __future__ import annotations

from ..errors import ProfileError
from ..profile import Profile


#: pinocchio's one-degree prismatic joint models (a URDF ``prismatic`` joint); every other joint
#: a namespace's kinematics takes is revolute (``revolute`` / ``continuous``)
_PRISMATIC = frozenset(("JointModelPX", "JointModelPY", "JointModelPZ", "JointModelPrismaticUnaligned"))


def check_kinematics(profile: Profile, source: str = "<profile>") -> list[str]:
    """Build every namespace's kinematics as the daemon will. Blocks (reads the URDFs, tens of
    ms each). Returns one 'namespace: base -> tip' line per cartesian namespace. Raises
    ProfileError naming ``source``, the profile key and what the URDF has instead."""
    from .kinematics import Kinematics, pin

    checked = []
    for i, ns in enumerate(profile.namespaces):
        k = ns.kinematics
        if k is None:
            continue
        where = f"namespaces[{i}] ({ns.name})"
        try:
            model = pin.buildModelFromUrdf(k.urdf)
        except Exception as exc:  # pinocchio raises ValueError / RuntimeError on bad XML
            raise ProfileError(f"{source}: {where}.kinematics.urdf: cannot build a model from "
                               f"{k.urdf}: {' '.join(str(exc).split())}") from exc
        links = [f.name for f in model.frames if f.type == pin.FrameType.BODY]
        for key, frame in (("base_frame", k.base_frame), ("tip_frame", k.tip_frame)):
            if not model.existFrame(frame):
                raise ProfileError(f"{source}: {where}.kinematics.{key}: {frame!r} is not a link of "
                                   f"{k.urdf} (its links: {', '.join(links)})")
        missing = [j for j in ns.joints if not model.existJointName(j)]
        if missing:
            raise ProfileError(
                f"{source}: {where}.joints: {', '.join(map(repr, missing))} not a joint of {k.urdf}, "
                f"which {where}.kinematics.urdf names (its joints: {', '.join(list(model.names)[1:])}); "
                f"rename the joint in the profile (joints[].name) or the URDF")
        for name in ns.joints:  # the profile's unit is the URDF's joint kind (a prismatic joint in m)
            kind = "prismatic" if model.joints[model.getJointId(name)].shortname() in _PRISMATIC else "revolute"
            i_joint = profile.joint_index(name)
            unit = profile.joints[i_joint].unit
            if unit != {"prismatic": "m", "revolute": "rad"}[kind]:
                raise ProfileError(
                    f"{source}: joints[{i_joint}] ({name}).unit: {unit!r}, but {k.urdf} makes {name} a {kind} "
                    f"joint: set unit: {'m' if kind == 'prismatic' else 'rad'}")
        try:
            Kinematics(k.urdf, k.base_frame, k.tip_frame, list(ns.joints))
        except ProfileError as exc:
            raise ProfileError(f"{source}: {where}.kinematics: {exc}") from exc
        checked.append(f"{ns.name}: {k.base_frame} -> {k.tip_frame}")
    return checked
