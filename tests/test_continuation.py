"""The records of qpscale/continuation.py (formulations/puncture.md sec. 4): what a path's stability
probe found, as the command line's ``branch`` object (docs/cli.md)."""

from __future__ import annotations

import json

from qpscale.continuation import BranchRecord
from qpscale.events import Branch, ContactChange
from qpscale.experiments.puncture import Candidate


def test_a_branch_record_gives_the_json_keys_in_order_and_leaves_out_what_is_unset():
    assert BranchRecord("off").to_dict() == {"check": "off", "branched": False}
    held = BranchRecord(
        "second variation",
        mirror=True,
        branched=True,
        delta_branch=(0.1, 0.2),
        min_eigenvalue=-1e-6,
        followed="asymmetric",
        asymmetry_at_failure=0.03,
    )
    out = held.to_dict()
    assert list(out) == [
        "check",
        "mirror",
        "branched",
        "delta_branch",
        "min_eigenvalue",
        "followed",
        "asymmetry_at_failure",
    ]
    assert out["delta_branch"] == [0.1, 0.2]
    json.dumps(Candidate((1.0, -1.0), 1.3, held).to_dict())


def test_a_free_paths_record_is_its_first_confirmed_branch():
    events = [
        ContactChange((0.0, 0.1), ((0, 1),)),
        Branch(0.2, -2e-6, 0.0, confirmed=False),
        Branch(0.3, -3e-6, 1e-4),
        Branch(0.4, -4e-6, 2e-4),
    ]
    record = BranchRecord.of_events(events, check=True)
    expected = BranchRecord("second variation", branched=True, delta_branch=0.3, followed="lower-energy side")
    assert record == expected
    assert list(record.to_dict()) == ["check", "branched", "delta_branch", "followed"]
    unconfirmed = BranchRecord.of_events(events[:2], check=True)
    assert unconfirmed.to_dict() == {"check": "second variation", "branched": False}
