"""The paper's planar two-joint arm written as a URDF (for equality tests against the planar model).

The arm moves in the vertical x-z plane of the base: both joints turn about
``-y``, so ``q_1 = 0`` points link 1 along ``+x`` (horizontal) and positive
angles raise it, as SPEC section 1 measures ``q_1`` from the horizontal with
gravity along ``-y`` of its own plane (here ``-z``). Each link is massless with
a point mass at its distal end: link ``i`` has its mass at ``(l_i, 0, 0)`` of
its frame, and joint 2 sits at the end of link 1. Joint limits are required by
URDF for revolute joints and are not read by the dynamics.
"""


def arm2_urdf(m1=12.0, m2=10.0, l1=1.5, l2=1.0, inertia=0.0, name="arm2"):
    """URDF text of the planar two-joint arm (masses kg, lengths m, rotational inertia kg m^2).

    ``inertia`` is each point mass's rotational inertia about its centre (the
    same on all axes); 0 gives the paper's point masses.
    """

    def link(label, mass, length):
        return (
            f'<link name="{label}"><inertial><origin xyz="{length!r} 0 0"/>'
            f'<mass value="{mass!r}"/><inertia ixx="{inertia!r}" iyy="{inertia!r}" '
            f'izz="{inertia!r}" ixy="0" ixz="0" iyz="0"/></inertial></link>'
        )

    limit = '<limit lower="-3.15" upper="3.15" effort="1000" velocity="10"/>'  # URDF needs one
    return f"""<robot name="{name}">
  <link name="base"/>
  {link("link1", m1, l1)}
  {link("link2", m2, l2)}
  <joint name="joint1" type="revolute">
    <parent link="base"/><child link="link1"/><origin xyz="0 0 0"/><axis xyz="0 -1 0"/>{limit}
  </joint>
  <joint name="joint2" type="revolute">
    <parent link="link1"/><child link="link2"/><origin xyz="{l1!r} 0 0"/><axis xyz="0 -1 0"/>{limit}
  </joint>
</robot>
"""
