"""Check the mesh-free arm descriptions in ``src/rmijax/robots/descriptions`` by hand.

Not a pytest module (it needs MuJoCo, Pinocchio and, for step 2, a copy of the MuJoCo
Menagerie). Run::

    python tests/robots/check_descriptions.py [--menagerie PATH/TO/mujoco_menagerie]

Steps, per arm (panda, iiwa14, ur5e):

0. The file uses only the explicit subset the stdlib reader of rmijax understands.
1. MuJoCo compiles it: number of dofs (7, 7, 6), gravity 0 0 -9.81.
2. (with ``--menagerie`` or ``$MENAGERIE_DIR``) Equivalence with the menagerie source: the
   source model is compiled with <asset>, geoms, sites, lights, cameras, actuators, tendons,
   equalities, contacts and sensors removed (and, for the Panda, the ``hand`` subtree), after
   checking that every moving body of the source has an explicit <inertial>. The compiled
   inertial/kinematic parameters are compared, then MuJoCo's mass matrix (``mj_fullM``,
   armature included) and ``qfrc_bias`` at 20 random states.
3. Pinocchio (``pin.buildModelFromMJCF``) loads the file; its ``crba`` (symmetrised) and
   ``nonLinearEffects`` are compared with MuJoCo's at the same states. Whether Pinocchio's MJCF
   reader fills ``model.armature`` and whether ``crba`` adds it are reported, and the armature is
   added by hand when it does not.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np

ROOT = Path(__file__).resolve().parents[2]
DESC = ROOT / "src" / "rmijax" / "robots" / "descriptions"

# name -> (description file, dofs, [(menagerie source path, subtree to drop, qpos size)])
ARMS = {
    "panda": (
        "panda.xml",
        7,
        [
            ("franka_emika_panda/panda.xml", "hand", 7),
            ("franka_emika_panda/panda_nohand.xml", None, 7),
        ],
    ),
    "iiwa14": ("iiwa14.xml", 7, [("kuka_iiwa_14/iiwa14.xml", None, 7)]),
    "ur5e": ("ur5e.xml", 6, [("universal_robots_ur5e/ur5e.xml", None, 6)]),
}

ALLOWED = {
    "mujoco": {"model"},
    "compiler": {"angle", "autolimits"},
    "worldbody": set(),
    "body": {"name", "pos", "quat"},
    "inertial": {"pos", "quat", "mass", "diaginertia", "fullinertia"},
    "joint": {"name", "type", "axis", "range", "armature", "pos"},
    "keyframe": set(),
    "key": {"name", "qpos"},
}
N_STATES = 20
RTOL_SOURCE = 1e-10
RTOL_PIN = 1e-9


def rel(a, b):
    """Relative error ||a - b|| / max(||b||, tiny)."""
    return float(np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-300))


def check_subset(path: Path) -> None:
    root = ET.parse(path).getroot()
    assert root.tag == "mujoco", root.tag
    for el in root.iter():
        if not isinstance(el.tag, str):  # comments
            continue
        assert el.tag in ALLOWED, f"{path.name}: element <{el.tag}> outside the subset"
        extra = set(el.attrib) - ALLOWED[el.tag]
        assert not extra, f"{path.name}: <{el.tag}> has attributes {extra} outside the subset"
    for body in root.iter("body"):
        joints = body.findall("joint")
        assert len(joints) <= 1, f"{path.name}: body {body.get('name')} has {len(joints)} joints"
        assert body.find("inertial") is not None, f"{path.name}: {body.get('name')} no inertial"
        for j in joints:
            assert j.get("type") == "hinge"
            for a in ("name", "axis", "range", "armature"):
                assert j.get(a) is not None, f"{path.name}: joint {j.get('name')} lacks {a}"


def states(m: mujoco.MjModel, rng: np.random.Generator, n: int):
    lo, hi = m.jnt_range[:, 0], m.jnt_range[:, 1]
    for _ in range(n):
        yield rng.uniform(lo, hi), rng.normal(0.0, 1.5, m.nv)


def mj_dyn(m: mujoco.MjModel, q, v):
    d = mujoco.MjData(m)
    d.qpos[:] = q
    d.qvel[:] = v
    mujoco.mj_forward(m, d)
    M = np.zeros((m.nv, m.nv))
    if hasattr(d, "qM"):  # MuJoCo < 3.4: mj_fullM(m, dst, qM)
        mujoco.mj_fullM(m, M, d.qM)
    else:  # newer: mj_fullM(m, d, dst)
        mujoco.mj_fullM(m, d, M)
    return M, d.qfrc_bias.copy()


# ---------------------------------------------------------------- source stripping (step 2)
STRIP_TOP = ("asset", "actuator", "tendon", "equality", "contact", "sensor", "option", "visual")
STRIP_ANY = ("geom", "site", "light", "camera")


def moving_bodies_without_inertial(root: ET.Element) -> list[str]:
    return [
        b.get("name")
        for b in root.iter("body")
        if (b.find("joint") is not None or b.find("freejoint") is not None)
        and b.find("inertial") is None
    ]


def stripped_source(src: Path, drop_subtree: str | None, nq: int) -> str:
    root = ET.parse(src).getroot()
    for tag in STRIP_TOP:
        for el in root.findall(tag):
            root.remove(el)
    for parent in list(root.iter()):
        for child in list(parent):
            if child.tag in STRIP_ANY:
                parent.remove(child)
            elif child.tag == "body" and child.get("name") == drop_subtree:
                parent.remove(child)
    comp = root.find("compiler")
    if comp is not None:
        comp.attrib.pop("meshdir", None)
    for key in root.iter("key"):
        key.attrib.pop("ctrl", None)
        if key.get("qpos") is not None:
            key.set("qpos", " ".join(key.get("qpos").split()[:nq]))
    return ET.tostring(root, encoding="unicode")


def compare_compiled(ma: mujoco.MjModel, mb: mujoco.MjModel) -> float:
    """Largest absolute difference of the compiled tree parameters (moving bodies and dofs)."""
    assert ma.nv == mb.nv and ma.nbody == mb.nbody, (ma.nbody, mb.nbody)
    fields = ["body_pos", "body_quat", "body_mass", "body_inertia", "body_ipos", "body_iquat"]
    worst = 0.0
    for f in fields:
        worst = max(worst, float(np.max(np.abs(getattr(ma, f)[1:] - getattr(mb, f)[1:]))))
    for f in ["jnt_axis", "jnt_range", "jnt_pos", "dof_armature"]:
        worst = max(worst, float(np.max(np.abs(getattr(ma, f) - getattr(mb, f)))))
    assert list(ma.jnt_type) == list(mb.jnt_type)
    for i in range(ma.njnt):
        assert ma.joint(i).name == mb.joint(i).name
    return worst


# ---------------------------------------------------------------- pinocchio (step 3)
def pin_check(path: Path, m: mujoco.MjModel, rng: np.random.Generator) -> dict:
    import pinocchio as pin

    pm = pin.buildModelFromMJCF(str(path))
    pd = pm.createData()
    assert pm.nq == m.nq and pm.nv == m.nv, (pm.nq, pm.nv)
    names = [pm.names[i] for i in range(1, pm.njoints)]
    mj_names = [m.joint(i).name for i in range(m.njnt)]
    assert names == mj_names, (names, mj_names)
    arm_pin = np.asarray(pm.armature).copy()
    q0 = pin.neutral(pm)
    M0 = pin.crba(pm, pd, q0).copy()
    pm0 = pin.buildModelFromMJCF(str(path))
    pm0.armature[:] = 0.0
    M0_noarm = pin.crba(pm0, pm0.createData(), q0).copy()
    # None when the model has no armature (nothing to tell)
    crba_adds = bool(np.allclose(np.diag(M0 - M0_noarm), arm_pin)) if np.any(arm_pin) else None
    add = np.zeros(m.nv) if np.any(arm_pin) else m.dof_armature.copy()
    if np.any(arm_pin) and not crba_adds:
        add = arm_pin
    eM = eb = 0.0
    for q, v in states(m, rng, N_STATES):
        Mj, bj = mj_dyn(m, q, v)
        Mp = pin.crba(pm, pd, q).copy()
        Mp = np.triu(Mp) + np.triu(Mp, 1).T + np.diag(add)
        bp = pin.nonLinearEffects(pm, pd, q, v).copy()
        eM, eb = max(eM, rel(Mp, Mj)), max(eb, rel(bp, bj))
    return {
        "pin_armature": arm_pin,
        "crba_includes_armature": crba_adds,
        "gravity": np.asarray(pm.gravity.linear).copy(),
        "rel_M": eM,
        "rel_bias": eb,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--menagerie", default=os.environ.get("MENAGERIE_DIR"))
    ap.add_argument("--no-pinocchio", action="store_true")
    args = ap.parse_args()
    ok = True
    for name, (fname, ndof, sources) in ARMS.items():
        path = DESC / fname
        print(f"== {name}: {path.relative_to(ROOT)}")
        check_subset(path)
        m = mujoco.MjModel.from_xml_path(str(path))
        assert m.nv == ndof and m.nq == ndof and m.nu == 0, (m.nv, m.nq)
        assert np.array_equal(m.opt.gravity, [0.0, 0.0, -9.81]), m.opt.gravity
        moving = [m.body(i).name for i in range(1, m.nbody) if m.body_jntnum[i] > 0]
        print(f"  subset ok; mujoco: nv={m.nv}, gravity={m.opt.gravity.tolist()}")
        print("  moving-body masses:", {b: float(m.body(b).mass[0]) for b in moving})
        total = sum(float(m.body(b).mass[0]) for b in moving)
        print(f"  total moving mass: {total:.6f} kg")
        print("  armature:", m.dof_armature.tolist(), " damping:", m.dof_damping.tolist())
        if m.nkey:
            print("  keyframe home:", m.key_qpos[0].tolist())

        if args.menagerie:
            for rel_src, drop, nq in sources:
                src = Path(args.menagerie) / rel_src
                if not src.exists():
                    print(f"  [source] {rel_src}: not found, skipped")
                    continue
                missing = moving_bodies_without_inertial(ET.parse(src).getroot())
                if drop:
                    missing = [b for b in missing if b not in ("left_finger", "right_finger")]
                if missing:
                    print(f"  [source] moving bodies WITHOUT explicit inertial: {missing}")
                    ok = False
                xml = stripped_source(src, drop, nq)
                with tempfile.NamedTemporaryFile("w", suffix=".xml", delete=False) as fh:
                    fh.write(xml)
                ms = mujoco.MjModel.from_xml_path(fh.name)
                os.unlink(fh.name)
                dpar = compare_compiled(m, ms)
                rng = np.random.default_rng(0)
                eM = eb = 0.0
                for q, v in states(m, rng, N_STATES):
                    Ma, ba = mj_dyn(m, q, v)
                    Mb, bb = mj_dyn(ms, q, v)
                    eM, eb = max(eM, rel(Ma, Mb)), max(eb, rel(ba, bb))
                same_key = (ms.nkey == m.nkey) and np.array_equal(ms.key_qpos, m.key_qpos)
                good = eM < RTOL_SOURCE and eb < RTOL_SOURCE and dpar == 0.0 and same_key
                ok &= good
                print(
                    f"  [source] {rel_src}: params max|diff|={dpar:.1e}, "
                    f"rel M={eM:.1e}, rel bias={eb:.1e}, keyframe equal={same_key}, "
                    f"source damping={ms.dof_damping.tolist()} -> {'OK' if good else 'FAIL'}"
                )
        else:
            print("  [source] skipped (no --menagerie / MENAGERIE_DIR)")

        if not args.no_pinocchio:
            r = pin_check(path, m, np.random.default_rng(1))
            good = r["rel_M"] < RTOL_PIN and r["rel_bias"] < RTOL_PIN
            ok &= good
            print(
                f"  [pinocchio] model.armature={r['pin_armature'].tolist()}, "
                f"crba includes armature={r['crba_includes_armature']} (None: all zero), "
                f"gravity={r['gravity'].tolist()}"
            )
            print(
                f"  [pinocchio] rel M={r['rel_M']:.1e}, rel nle={r['rel_bias']:.1e} "
                f"-> {'OK' if good else 'FAIL'}"
            )
    print("ALL OK" if ok else "SOME CHECKS FAILED")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
