"""The right unit (issue 14, part 1), the decisions alone: service.identity.UnitCheck driven without a
station, as the engine drives it (an Identify step's reply, then the operator's answers to its prompts).
The REST API's end-to-end cases are in test_right_unit.py."""

from __future__ import annotations

from typing import Any

import pytest

from procedures.steps import Identify, Move, Outcome, Procedure, Prompt
from service.identity import UnitCheck


def _procedure() -> Procedure:
    def run(params: Any):  # one table step: the check settles every slot before it
        yield Move(0.0)
        return Outcome()
    return Procedure("p", "1", object, run)  # type: ignore[arg-type]


def decide(typed: dict[int, str], reported: dict[int, str | None], answers: dict[int, str] | None = None,
           policy: str = "prompt", known: set[str] = frozenset()) -> tuple[dict[int, Any], list[str]]:
    """Run the check; ``reported``: what each slot's unit reports (None: it refuses the ID command);
    ``known``: serials whose unit reported its own when calibrated before. The identities, and the prompts' texts."""
    check = UnitCheck(typed=typed, slots=sorted(set(typed) | set(reported)), policy=policy,
                      reports_itself=lambda serial: serial in known)
    gen = check.procedure(_procedure()).run(None)
    prompts, reply = [], None
    try:
        while True:
            step = gen.send(reply)
            if isinstance(step, Identify):
                reply = {s: ("PX", r, "1.0") for s, r in reported.items() if r is not None}
            elif isinstance(step, Prompt):
                prompts.append(step.text)
                reply = (answers or {})[int(step.id.split("-")[1])]
            else:
                reply = None
    except StopIteration:
        pass
    return check.identities, prompts


def test_typed_at_the_prompt_does_not_file_a_unit_under_a_serial_whose_unit_reports_its_own() -> None:
    """An outside prober typed SN-A2 for unit SN-B1 and answered 'typed': SN-A2's current calibration became
    SN-B1's data, without a warning (trust-typed refused exactly this). The prompt says so, and 'typed' is
    refused; 'identified' still certifies the unit as itself."""
    ids, prompts = decide({0: "SN-A2"}, {0: "SN-B1"}, {0: "typed"}, known={"SN-A2"})
    assert "reports its own serial number" in prompts[0] and "'typed' would leave this unit uncalibrated" in prompts[0]
    assert not ids[0].certify and "the operator answered 'typed', but unit SN-A2 reports its own" in ids[0].note
    ids, _ = decide({0: "SN-A2"}, {0: "SN-B1"}, {0: "identified"}, known={"SN-A2"})
    assert ids[0].certify and ids[0].serial == "SN-B1"
    ids, _ = decide({0: "SN-A2"}, {0: "SN-B1"}, {0: "typed"})  # an unknown serial: the operator's word stands
    assert ids[0].certify and ids[0].serial == "SN-A2"


@pytest.mark.parametrize("policy", ["prompt", "trust-typed"])
def test_two_swapped_units_are_not_certified_under_each_other_s_serials(policy: str) -> None:
    """Two slots with the units swapped: slot 0 typed SN-A2 reports SN-A1, slot 1 typed SN-A1 reports SN-A2.
    Answering 'typed' for slot 0 certified it as SN-A2, and the real SN-A2 in slot 1 was then a "duplicate"
    whose note said both "certified as SN-A2" and "not certified". The typed serial that another slot reports
    is not certified for this one; each unit is certified as itself on 'identified'."""
    ids, prompts = decide({0: "SN-A2", 1: "SN-A1"}, {0: "SN-A1", 1: "SN-A2"}, {0: "typed", 1: "typed"}, policy)
    assert not ids[0].certify and not ids[1].certify
    assert "unit SN-A2 is the one in slot 1 (it reports SN-A2)" in ids[0].note
    if policy == "prompt":
        assert "Unit SN-A2 is the one in slot 1" in prompts[0]
        ids, _ = decide({0: "SN-A2", 1: "SN-A1"}, {0: "SN-A1", 1: "SN-A2"}, {0: "identified", 1: "identified"})
        assert [(i.certify, i.serial) for _, i in sorted(ids.items())] == [(True, "SN-A1"), (True, "SN-A2")]


def test_a_duplicate_s_note_does_not_say_certified() -> None:
    """One unit's serial typed for one slot and reported by another's unit (trust-typed): the second is not
    certified, and its note no longer begins with "certified as" before saying "not certified"."""
    ids, _ = decide({0: "SN-C", 1: "SN-D"}, {0: "SN-C", 1: "SN-C"}, policy="trust-typed")
    assert ids[0].certify and not ids[1].certify
    assert "certified as SN-C (serial" not in ids[1].note and ids[1].note.endswith("not certified"), ids[1].note


@pytest.mark.parametrize("policy, answer, certified", [("refuse", None, False), ("trust-typed", None, True),
                                                       ("prompt", "typed", True), ("prompt", "skip", False)])
def test_a_unit_that_cannot_identify_itself_typed_as_a_known_unit_is_settled_by_the_policy(
        policy: str, answer: str | None, certified: bool) -> None:
    """A compass that refuses the ID command, typed as SN-A1 (a unit that reported its own when calibrated):
    it was certified and superseded SN-A1's calibration even under 'refuse', with no policy recorded. The
    policy settles it now, and says so; a serial nobody knows is calibrated as typed, as before."""
    ids, prompts = decide({0: "SN-A1"}, {0: None}, {0: answer} if answer else None, policy, known={"SN-A1"})
    assert ids[0].certify is certified and ids[0].status == "not identified" and ids[0].policy == policy
    assert "reports its own (calibrated before as SN-A1)" in ids[0].note
    assert bool(prompts) is (policy == "prompt")
    ids, prompts = decide({0: "SN-NEW"}, {0: None}, policy="refuse", known={"SN-A1"})
    assert ids[0].certify and not prompts and ids[0].note.endswith("certified as the typed SN-NEW")
