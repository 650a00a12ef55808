"""The serial-chain dynamics against Pinocchio, an independent rigid-body library.

The same chain is built in Pinocchio from the description's numbers (placements, joint axes,
mass, centre of mass and inertia about it); CRBA must give our M and RNEA our inverse dynamics.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

import cochlea
from cochlea.robots.serial.description import joint_rotation, load_serial

from .conftest import DATA, ev, random_state

CASES = [("serial", "arm1"), ("serial", "arm2"), (DATA / "general_chain.toml", "chain")]


def pinocchio_arm(system, arm):
    model = pin.Model()
    parent = 0
    for link in arm.links:
        joint = link.joint
        placement = pin.SE3(joint_rotation(joint), joint.origin_xyz)
        if joint.type == "revolute":
            joint_model = pin.JointModelRevoluteUnaligned(joint.axis)
        else:
            joint_model = pin.JointModelPrismaticUnaligned(joint.axis)
        parent = model.addJoint(parent, joint_model, placement, link.name)
        model.appendBodyToJoint(parent, pin.Inertia(link.mass, link.com, link.inertia_com),
                                pin.SE3.Identity())
    model.gravity.linear = arm.base_rotation.T @ system.gravity
    return model


@pytest.mark.parametrize("source,arm_name", CASES, ids=["arm1", "arm2", "general"])
def test_crba_and_rnea_agree(source, arm_name, rng):
    system = load_serial(source)
    arm = system.arm(arm_name)
    ours = cochlea.model("serial", arm=arm_name, description=source)
    theirs = pinocchio_arm(system, arm)
    data = theirs.createData()
    for _ in range(100):
        q, qd, qdd = random_state(rng, ours.nq)
        M_pin = pin.crba(theirs, data, q)
        M_pin = np.triu(M_pin) + np.triu(M_pin, 1).T  # crba fills the upper triangle
        tau_pin = pin.rnea(theirs, data, q, qd, qdd)
        assert np.abs(ev(ours.M, q) - M_pin).max() < 1e-10
        assert np.abs(ev(ours.inverse_dynamics, q, qd, qdd) - tau_pin).max() < 1e-10
        assert np.abs(ev(ours.G, q) - pin.computeGeneralizedGravity(theirs, data, q)).max() \
            < 1e-10


def test_the_general_chain_exercises_gravity_and_coupling(rng):
    """Guard: the oracle comparison is not vacuous (non-zero gravity, full coupling)."""
    ours = cochlea.model("serial", description=DATA / "general_chain.toml")
    q, _, _ = random_state(rng, ours.nq)
    assert np.abs(ev(ours.G, q)).min() > 1e-4
    assert np.abs(ev(ours.M, q)).min() > 1e-6
