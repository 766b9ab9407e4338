"""The arm's URDF, from its config (``armfusion info --urdf ARM.urdf``), for
robot_state_publisher: with the joint states armfusion publishes it gives every link's and
every sensor's frame in TF.

The arm model's chain (:class:`armfusion.models.arm.Joint`): joint i is a fixed transform ``T_pre``, a
turn about ``axis`` by ``q + offset``, then a fixed ``T_post``; link i's frame is after
``T_post``. A URDF joint is a fixed origin then a turn by ``q`` about its axis, the child
link's frame right after it. So URDF joint i's origin is ``T_post(i-1) T_pre(i) Rot(axis,
offset)`` (a turn about the axis commutes with the turn by ``q``), the URDF link ``<joint>_link``
is the model's link before its ``T_post``, and the last ``T_post`` is a fixed joint to the
``flange`` link. Each sensor is a fixed joint from its link to a link of its own name (the
frame id of its messages): ``T_post(L) T_LS``; a sensor on link 0 hangs from the base
(:data:`~armfusion.fusion.ros2.estimates_bag.BASE_FRAME`). Joints keep the config's names and limits;
the links carry no geometry (armfusion knows the chain, not the shapes).
"""

from __future__ import annotations

from xml.sax.saxutils import quoteattr

import numpy as np
from armfusion.fusion.ros2.estimates_bag import BASE_FRAME
from armfusion.models.arm import ArmModel
from armfusion.models.rotations import exp_so3, rpy_from_R

FLANGE_LINK = "flange"


def _rpy(R: np.ndarray) -> np.ndarray:
    """URDF's rpy (``R = Rz(y) Ry(p) Rx(r)``) of ``R``, also at pitch +-90 deg (roll then 0)."""
    if abs(R[2, 0]) < 1.0 - 1e-12:
        return rpy_from_R(R)
    pitch = -np.copysign(np.pi / 2, R[2, 0])
    return np.array([0.0, pitch, np.arctan2(-R[0, 1], R[1, 1])])


def _origin(R: np.ndarray, p: np.ndarray) -> str:
    xyz = " ".join(f"{v:.17g}" for v in p)
    rpy = " ".join(f"{v:.17g}" for v in _rpy(R))
    return f'<origin xyz="{xyz}" rpy="{rpy}"/>'


def link_name(arm: ArmModel, link: int) -> str:
    """The URDF link of the model's link ``link`` (0: the base)."""
    return BASE_FRAME if link == 0 else f"{arm.joints[link - 1].name}_link"


def _comment_text(text: str) -> str:
    """``text`` as an XML comment may hold it: no ``--`` (a comment that holds one is not XML:
    no parser reads the file), no ``-`` at its end."""
    while "--" in text:
        text = text.replace("--", "-")
    return text.rstrip("-")


def urdf_from_arm(arm: ArmModel) -> str:
    """The URDF text of ``arm`` (see the module's docstring)."""
    made = _comment_text(f"from {arm.source or 'an armfusion config'} by armfusion info")
    lines = ['<?xml version="1.0"?>', f"<robot name={quoteattr(arm.name)}>", f"  <!-- {made} -->",
             f"  <link name={quoteattr(BASE_FRAME)}/>"]
    R_post, p_post = np.eye(3), np.zeros(3)  # the previous joint's post transform
    for i, j in enumerate(arm.joints):
        axis = np.asarray(j.axis, float)
        R = R_post @ np.asarray(j.R_pre) @ exp_so3(axis * j.offset_rad)
        p = R_post @ np.asarray(j.p_pre_m) + p_post
        child = link_name(arm, i + 1)
        lines += [f"  <link name={quoteattr(child)}/>",
                  f"  <joint name={quoteattr(j.name)} type=\"revolute\">",
                  f"    <parent link={quoteattr(link_name(arm, i))}/>",
                  f"    <child link={quoteattr(child)}/>",
                  f"    {_origin(R, p)}", f"    <axis xyz=\"{' '.join(f'{v:.17g}' for v in axis)}\"/>",
                  f"    <limit lower=\"{j.min_rad:.17g}\" upper=\"{j.max_rad:.17g}\" effort=\"0\" "
                  'velocity="0"/>',
                  "  </joint>"]
        R_post, p_post = np.asarray(j.R_post), np.asarray(j.p_post_m)
    if arm.joints:
        lines += [f"  <link name={quoteattr(FLANGE_LINK)}/>", '  <joint name="flange_joint" type="fixed">',
                  f"    <parent link={quoteattr(link_name(arm, arm.n_joints))}/>",
                  f"    <child link={quoteattr(FLANGE_LINK)}/>", f"    {_origin(R_post, p_post)}",
                  "  </joint>"]
    for s in arm.sensors:
        if s.link == 0:
            R, p = np.asarray(s.R_LS), np.asarray(s.p_L_m)
        else:
            j = arm.joints[s.link - 1]
            R = np.asarray(j.R_post) @ np.asarray(s.R_LS)
            p = np.asarray(j.R_post) @ np.asarray(s.p_L_m) + np.asarray(j.p_post_m)
        lines += [f"  <link name={quoteattr(s.name)}/>",
                  f"  <joint name={quoteattr(s.name + '_mount')} type=\"fixed\">",
                  f"    <parent link={quoteattr(link_name(arm, s.link))}/>",
                  f"    <child link={quoteattr(s.name)}/>",
                  f"    {_origin(R, p)}", "  </joint>"]
    lines.append("</robot>")
    return "\n".join(lines) + "\n"
