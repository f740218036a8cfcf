"""The URDF reader (``jaxflex.core.urdf``): a chain read from a URDF has the dynamics of the
same arm described by DH parameters, and MuJoCo's own reading of the same file agrees."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflex.core.urdf import UrdfChain, UrdfError, moved_phi, read_urdf, rpy_matrix
from jaxflex.io.arms import kuka_kr300_chain

jax.config.update("jax_enable_x64", True)


def matrix_rpy(R: np.ndarray) -> tuple[float, float, float]:
    """URDF's (roll, pitch, yaw) of a rotation (yaw 0 at the gimbal lock)."""
    p = math.asin(max(-1.0, min(1.0, -R[2, 0])))
    if abs(R[2, 0]) < 1.0 - 1e-12:
        return math.atan2(R[2, 1], R[2, 2]), p, math.atan2(R[1, 0], R[0, 0])
    return math.atan2(-R[1, 2], R[1, 1]), p, 0.0


def origin(T: np.ndarray) -> str:
    rpy = " ".join(f"{v:.17g}" for v in matrix_rpy(T[:3, :3]))
    xyz = " ".join(f"{v:.17g}" for v in T[:3, 3])
    return f'<origin xyz="{xyz}" rpy="{rpy}"/>'


def dh_post(a: float, d: float, alpha: float) -> np.ndarray:
    """Tz(d) Tx(a) Rx(alpha)."""
    ca, sa = math.cos(alpha), math.sin(alpha)
    return np.array([[1, 0, 0, a], [0, ca, -sa, 0], [0, sa, ca, d], [0, 0, 0, 1.0]])


def dh_as_urdf(chain, flange_mass: float = 0.0) -> str:
    """A URDF of a DH chain (``SerialChain``): link i's URDF frame is DH frame i-1 turned by
    joint i, so joint i's origin is the DH transform of link i-1 and its offset; link i's
    inertial is its DH inertia moved to that frame. With ``flange_mass``, a point-like flange
    welded to the last link by a fixed joint, its mass taken from the last link's."""
    a, d, al, off = (np.asarray(v, float) for v in (chain.a, chain.d, chain.alpha,
                                                    chain.offset))
    mass, com, Ic = (np.asarray(v, float) for v in (chain.mass, chain.com, chain.inertia_com))
    parts = ['<robot name="dh">', '<link name="base"/>']
    post = np.eye(4)
    for i, kind in enumerate(chain.joints):
        pre = np.eye(4)
        if kind == "R":
            c, s = math.cos(off[i]), math.sin(off[i])
            pre[:2, :2] = [[c, -s], [s, c]]
        else:
            pre[2, 3] = off[i]
        T = post @ pre
        parent = "base" if i == 0 else f"l{i}"
        jt = "revolute" if kind == "R" else "prismatic"
        parts.append(f'<joint name="j{i + 1}" type="{jt}"><parent link="{parent}"/>'
                     f'<child link="l{i + 1}"/>{origin(T)}<axis xyz="0 0 1"/>'
                     f'<limit lower="-3" upper="3" effort="1" velocity="1"/></joint>')
        post = dh_post(a[i], d[i], al[i])
        m = mass[i] - (flange_mass if i == chain.n - 1 else 0.0)
        Tin = post.copy()
        Tin[:3, 3] = post[:3, :3] @ com[i] + post[:3, 3]
        I = Ic[i] + np.eye(3) * 1e-9  # MuJoCo needs a positive inertia
        parts.append(
            f'<link name="l{i + 1}"><inertial>{origin(Tin)}<mass value="{m:.17g}"/>'
            f'<inertia ixx="{I[0, 0]:.17g}" ixy="{I[0, 1]:.17g}" ixz="{I[0, 2]:.17g}" '
            f'iyy="{I[1, 1]:.17g}" iyz="{I[1, 2]:.17g}" izz="{I[2, 2]:.17g}"/></inertial>'
            '</link>')
    if flange_mass:
        n = chain.n
        Tf = post.copy()
        Tf[:3, 3] = post[:3, :3] @ com[n - 1] + post[:3, 3]
        parts.append(f'<joint name="flange" type="fixed"><parent link="l{n}"/>'
                     f'<child link="flange"/>{origin(Tf)}</joint>')
        parts.append(f'<link name="flange"><inertial><mass value="{flange_mass}"/>'
                     '<inertia ixx="0" ixy="0" ixz="0" iyy="0" iyz="0" izz="0"/>'
                     '</inertial></link>')
    parts.append("</robot>")
    return "\n".join(parts)


def test_rpy_round_trip():
    rng = np.random.default_rng(0)
    for rpy in [*rng.uniform(-3, 3, (20, 3)), (0.3, math.pi / 2, -0.2), (1.0, -math.pi / 2, 0)]:
        R = rpy_matrix(rpy)
        assert np.allclose(rpy_matrix(matrix_rpy(R)), R, atol=1e-12)


def test_moved_phi_adds_as_bodies_do():
    """Two point masses described in a moved frame give the same standard parameters as
    described where they are."""
    rng = np.random.default_rng(1)
    R, p = rpy_matrix(rng.uniform(-2, 2, 3)), rng.uniform(-1, 1, 3)
    c, m = rng.uniform(-1, 1, 3), 2.5
    point = np.concatenate([[m], m * c, m * np.array([c[1]**2 + c[2]**2, -c[0] * c[1],
                                                      -c[0] * c[2], c[0]**2 + c[2]**2,
                                                      -c[1] * c[2], c[0]**2 + c[1]**2])])
    moved = moved_phi(point, R, p)
    c2 = R @ c + p
    assert moved[0] == pytest.approx(m)
    assert np.allclose(moved[1:4], m * c2)
    assert np.allclose(moved[4:], m * np.array([c2[1]**2 + c2[2]**2, -c2[0] * c2[1],
                                                -c2[0] * c2[2], c2[0]**2 + c2[2]**2,
                                                -c2[1] * c2[2], c2[0]**2 + c2[1]**2]))


@pytest.mark.parametrize("flange", [0.0, 7.0])
def test_kr300_from_urdf_has_its_dh_dynamics(flange):
    """The KR300 written as a URDF (offsets in the joint origins, a welded flange) reads back
    to the DH chain's M, C q', G and axis kinds at random poses."""
    dh = kuka_kr300_chain()
    chain = read_urdf(dh_as_urdf(dh, flange), gravity=dh.g)
    assert chain.joints == "RRRRRR" and chain.names == tuple(f"j{i}" for i in range(1, 7))
    rng = np.random.default_rng(2)
    q, dq = (jnp.asarray(rng.uniform(-2, 2, (3, 6))) for _ in range(2))
    terms = eqx.filter_jit(jax.vmap(lambda c, q, dq: (c.mass_matrix(q), c.gravity(q),
                                                      c.coriolis(q, dq, dq)),
                                    in_axes=(None, 0, 0)))
    for got, want in zip(terms(chain, q, dq), terms(dh, q, dq)):
        assert np.allclose(got, want, rtol=1e-9, atol=1e-6)
    assert chain.axis_kinds(q[0]) == dh.axis_kinds(q[0])


ARM = """<robot name="rpr">
  <link name="world_base"><inertial><mass value="50"/>
    <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <link name="pedestal"/>
  <link name="upper"><inertial><origin xyz="0.2 0.01 -0.03" rpy="0.1 0.2 0.3"/>
    <mass value="4.0"/><inertia ixx="0.05" ixy="0.001" ixz="-0.002" iyy="0.04" iyz="0.003"
    izz="0.03"/></inertial></link>
  <link name="slider"><inertial><origin xyz="0 0.05 0.1" rpy="0 0 0"/>
    <mass value="2.0"/><inertia ixx="0.02" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.015"/>
    </inertial></link>
  <link name="camera"><inertial><origin xyz="0.01 0 0" rpy="0 0 0"/><mass value="0.4"/>
    <inertia ixx="0.001" ixy="0" ixz="0" iyy="0.001" iyz="0" izz="0.001"/></inertial></link>
  <link name="wrist"><inertial><origin xyz="0.03 0 0.02" rpy="0.4 -0.1 0"/>
    <mass value="1.2"/><inertia ixx="0.004" ixy="0.0002" ixz="0" iyy="0.003" iyz="0"
    izz="0.002"/></inertial></link>
  <link name="tool"><inertial><origin xyz="0 0 0.05" rpy="0 0 0"/><mass value="0.8"/>
    <inertia ixx="0.002" ixy="0" ixz="0" iyy="0.002" iyz="0" izz="0.001"/></inertial></link>
  <joint name="mount" type="fixed"><parent link="world_base"/><child link="pedestal"/>
    <origin xyz="0 0 0.4" rpy="0 0 0.5"/></joint>
  <joint name="shoulder" type="revolute"><parent link="pedestal"/><child link="upper"/>
    <origin xyz="0.1 0 0.2" rpy="0.3 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-3" upper="3" effort="100" velocity="2"/></joint>
  <joint name="extend" type="prismatic"><parent link="upper"/><child link="slider"/>
    <origin xyz="0.4 0 0" rpy="0 0.2 0"/><axis xyz="1 0 0"/>
    <limit lower="-1" upper="1" effort="100" velocity="1"/></joint>
  <joint name="camera_mount" type="fixed"><parent link="upper"/><child link="camera"/>
    <origin xyz="0.1 0.1 0" rpy="0 0 1"/></joint>
  <joint name="wrist" type="continuous"><parent link="slider"/><child link="wrist"/>
    <origin xyz="0 0.1 0.2" rpy="0 0 0"/><axis xyz="0.6 0 0.8"/></joint>
  <joint name="tool_mount" type="fixed"><parent link="wrist"/><child link="tool"/>
    <origin xyz="0 0 0.1" rpy="0.5 0 0"/></joint>
</robot>"""


def test_urdf_chain_agrees_with_mujoco_reading_the_same_file():
    """MuJoCo's URDF import of an arm with a revolute, a prismatic and a continuous joint
    (an oblique axis), a welded base, a welded camera off the chain and a welded tool: its
    mass matrix and gravity torques equal the chain's at random poses."""
    mujoco = pytest.importorskip("mujoco")
    chain = read_urdf(ARM)
    assert chain.joints == "RPR" and chain.names == ("shoulder", "extend", "wrist")
    xml = ARM.replace("<robot name=\"rpr\">", "<robot name=\"rpr\"><mujoco><compiler "
                      "fusestatic=\"true\" discardvisual=\"true\"/></mujoco>")
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    assert model.nv == 3
    rng = np.random.default_rng(3)
    for _ in range(4):
        q = rng.uniform(-1, 1, 3)
        data.qpos[:] = q
        data.qvel[:] = 0.0
        mujoco.mj_forward(model, data)
        M = np.zeros((3, 3))
        mujoco.mj_fullM(model, data, M)
        assert np.allclose(chain.mass_matrix(jnp.asarray(q)), M, rtol=1e-8, atol=1e-10)
        assert np.allclose(chain.gravity(jnp.asarray(q)), data.qfrc_bias, rtol=1e-8,
                           atol=1e-10)


def test_urdf_chain_is_differentiable_in_its_inertias():
    chain = read_urdf(ARM)
    q = jnp.asarray([0.2, 0.1, -0.4])
    g = jax.grad(lambda phi: jnp.sum(chain.with_phi(phi).gravity(q) ** 2))(chain.phi)
    assert g.shape == (3, 10) and bool(jnp.all(jnp.isfinite(g)))
    batched = jax.vmap(chain.mass_matrix)(jnp.stack([q, 2 * q]))
    assert batched.shape == (2, 3, 3)
    assert isinstance(chain, UrdfChain)


@pytest.mark.parametrize("edit, words", [
    (("type=\"continuous\"", "type=\"floating\""), "floating"),
    (("<parent link=\"slider\"/>", "<parent link=\"nowhere\"/>"), "nowhere"),
    (("<mass value=\"2.0\"/>", "<mass value=\"-2.0\"/>"), "mass"),
    (("izz=\"0.015\"", "izz=\"oops\""), "izz"),
    (("</robot>", "<joint name=\"j\" type=\"revolute\"><parent link=\"upper\"/><child "
                  "link=\"extra\"/><axis xyz=\"0 0 1\"/></joint><link name=\"extra\"/>"
                  "</robot>"), "one path"),
    (("</robot>", "<robot>"), "XML"),
])
def test_a_urdf_that_is_not_a_chain_is_refused_by_name(edit, words):
    with pytest.raises(UrdfError, match=words):
        read_urdf(ARM.replace(*edit))


def test_moving_joints_off_one_path_are_refused_and_a_missing_file_is_named(tmp_path):
    branched = ARM.replace("</robot>", "<joint name=\"j\" type=\"revolute\"><parent "
                           "link=\"upper\"/><child link=\"extra\"/><axis xyz=\"0 0 1\"/>"
                           "</joint><link name=\"extra\"><inertial><mass value=\"1\"/>"
                           "</inertial></link></robot>")
    with pytest.raises(UrdfError, match="one path"):
        read_urdf(branched)
    path = tmp_path / "arm.urdf"
    path.write_text(ARM)
    assert read_urdf(path).n == 3
    with pytest.raises(UrdfError, match="not found"):
        read_urdf(tmp_path / "missing.urdf")


FRICTION3 = {"Fc": [0.1] * 3, "Fs": [0.15] * 3, "vs": [0.05] * 3, "sigma0": [100.0] * 3,
             "sigma1": [0.1] * 3, "sigma2": [0.2] * 3}


def test_a_parameter_file_names_a_urdf_beside_it_and_a_dh_table(tmp_path):
    """``links`` of type "urdf" (a path relative to the file) and "dh" build the plant's
    links; its energy balance holds through the flexible plant's vector field (dE/dt is the
    power of the applied torque less the friction's); refusals name the field."""
    import json

    from jaxflex.core.state import PlantState
    from jaxflex.io.params import Params, ParamsError, load_params

    (tmp_path / "robot").mkdir()
    (tmp_path / "robot" / "arm.urdf").write_text(ARM)
    d = {"links": {"type": "urdf", "path": "robot/arm.urdf", "gravity": [0.0, 0.0, -9.81]},
         "plant": {"J": [0.01, 0.02, 0.005], "K": [200.0, 300.0, 50.0]},
         "friction": FRICTION3}
    (tmp_path / "p.json").write_text(json.dumps(d))
    params = load_params(tmp_path / "p.json")
    plant = params.to_plant()
    assert isinstance(plant.links, UrdfChain) and plant.n == 3
    x = PlantState(q1=jnp.array([0.2, 0.1, -0.3]), dq1=jnp.array([0.5, -0.2, 1.0]),
                   q2=jnp.array([0.25, 0.12, -0.2]), dq2=jnp.array([0.4, 0.0, 0.8]),
                   z=jnp.zeros(3))
    tau = jnp.array([1.0, -2.0, 0.5])
    dE = jax.jvp(plant.energy, (x,), (plant.vector_field(x, tau),))[1]
    power = tau @ x.dq2 - plant.friction_torque(x) @ x.dq1
    assert float(dE) == pytest.approx(float(power), rel=1e-8, abs=1e-10)
    chain = kuka_kr300_chain()
    dh = {"type": "dh", "a": list(map(float, chain.a)), "d": list(map(float, chain.d)),
          "alpha": list(map(float, chain.alpha)), "offset": list(map(float, chain.offset)),
          "mass": list(map(float, chain.mass)), "com": np.asarray(chain.com).tolist(),
          "inertia": np.asarray(chain.inertia_com).tolist(), "gravity": [0.0, 0.0, 9.81]}
    six = {k: [v[0]] * 6 for k, v in FRICTION3.items()}
    p6 = Params.from_dict({"links": dh, "plant": {"J": [1.0] * 6, "K": [1e5] * 6},
                           "friction": six})
    q = jnp.linspace(-1.0, 1.0, 6)
    assert np.allclose(p6.to_plant().links.mass_matrix(q), chain.mass_matrix(q), rtol=1e-9)
    assert Params.from_dict(json.loads(json.dumps(p6.to_dict()))).to_dict() == p6.to_dict()
    for links, words in (({**d["links"], "path": str(tmp_path / "none.urdf")}, "not found"),
                         ({**d["links"], "path": 3.0}, "links.path: expected text"),
                         ({**d["links"], "tip": "tool"}, "unknown field 'tip'"),
                         ({**dh, "mass": [-1.0] + dh["mass"][1:]}, "mass"),
                         ({k: v for k, v in dh.items() if k != "com"}, "missing field")):
        with pytest.raises(ParamsError, match=words):
            Params.from_dict({**d, "links": links, "plant": d["plant"] if links.get(
                "type") == "urdf" else {"J": [1.0] * 6, "K": [1e5] * 6},
                "friction": FRICTION3 if links.get("type") == "urdf" else six}).to_plant()
