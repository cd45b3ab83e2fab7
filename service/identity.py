"""Which unit is on the fixture: the serial number a unit reports against the one typed.

A run names its units once they are mounted, before the table's first step with them (a calibration
right away; a batch's unit after its mount prompt, which the table awaits at its load pose). For each slot:

- the unit reports no serial number (an empty one, or it refuses the ID command), or an answer that is no
  serial number (:func:`check_serial`, the rule every serial number here follows): ``not identified``;
  the typed serial is used as before, and the result and the certificate say so; with none typed the
  slot is not calibrated (nothing to store it under), which a run of one unit says before the table moves;
  typed as a serial whose unit reports its own (calibrated before as itself), the policy settles it as
  for a differing serial (``prompt``: 'typed' or 'skip');
- it reports the typed one, or none was typed: ``identified``;
- it reports another one: ``differs``, settled by the serial policy (the request's, else the
  station's): ``prompt`` asks the operator (answers ``typed``, ``identified`` or ``skip``), ``refuse``
  leaves the slot uncalibrated with the reason, ``trust-typed`` certifies the typed serial and records
  what the unit reported; neither ``trust-typed`` nor the operator's 'typed' certifies it when the typed
  serial is another unit's (one known to report its own, or the one another slot of the run reports): this
  unit, reporting another, is not that one; a serial typed in another letter case is the one it reports;
- it reports a serial already certified earlier in the same batch (or in another slot of the run):
  ``duplicate``, the same physical unit mounted again; not certified, whatever the policy;
- it would be certified under a serial another unit of the batch (or of the run) is already
  certified under: ``duplicate`` too, not certified (one serial is one unit). A unit whose calibration
  was rejected (FAIL) counts as not certified: it may be mounted again for a retest.

No I/O here: :class:`UnitCheck` wraps a procedure's generator with the steps that do it (an
:class:`~procedures.steps.Identify` and the operator prompts), which the engine runs.
"""

from __future__ import annotations

import re
import string
from collections.abc import Callable, Generator
from dataclasses import dataclass, field
from typing import Any, Literal, get_args

from procedures.steps import TIMED_STEPS, Identify, Outcome, Procedure, ProcedureGen, Prompt, Reply

#: What a run does when a unit reports another serial number than the one typed.
SerialPolicy = Literal["prompt", "refuse", "trust-typed"]
POLICIES: tuple[str, ...] = get_args(SerialPolicy)
DEFAULT_POLICY = "prompt"
#: The answers to a serial prompt.
CHOICES = ("typed", "identified", "skip")
#: Serial prompts are named ``serial-SLOT``.
PROMPT_PREFIX = "serial-"


#: Longest serial number (``devices.serial``).
SERIAL_MAX = 64
#: A serial number's characters: printable ASCII letters, digits, ``- _ . : + #`` and (inside) the space.
SERIAL_CHARS = frozenset(string.ascii_letters + string.digits + "-_.:+# ")
SERIAL_PATTERN = r"^[A-Za-z0-9_.:+#-]([A-Za-z0-9_.:+# -]*[A-Za-z0-9_.:+#-])?$"
SERIAL_RULE = ("1 to 64 printable ASCII characters: letters, digits, '-', '_', '.', ':', '+', '#' and spaces "
               "between them (no '/', no control or non-ASCII characters)")


def check_serial(value: str) -> str:
    """A serial number as stored: spaces at either end dropped, then 1 to 64 characters of
    :data:`SERIAL_CHARS`, so it fits ``devices.serial`` on both databases, reads back through
    ``/devices/{serial}`` and can name a file. ValueError names the problem."""
    if "\x00" in value:
        raise ValueError("contains a NUL character (\\x00)")
    v = value.strip(" ")
    if not v:
        raise ValueError("empty serial number")
    if len(v) > SERIAL_MAX:
        raise ValueError(f"serial number of {len(v)} characters; at most {SERIAL_MAX}")
    bad = next((c for c in v if c not in SERIAL_CHARS), None)
    if bad is not None:
        raise ValueError(f"character {bad!r} at position {v.index(bad) + 1} is not allowed in a serial number: "
                         + SERIAL_RULE)
    return v


def is_serial_prompt(prompt_id: str) -> bool:
    """Whether a prompt asks the operator which serial number a unit is certified under."""
    return prompt_id.startswith(PROMPT_PREFIX)


def normalise(answer: str) -> str:
    """An operator's answer as compared with :data:`CHOICES` (case and spaces ignored)."""
    return answer.strip().lower()


@dataclass
class Identity:
    """What a slot's unit reported and what was decided about its serial number."""

    slot: int
    typed: str | None  # the request's serial number (None: none typed)
    identified: str | None  # what the unit reported (None: not identified)
    status: str  # not identified | identified | differs | duplicate
    serial: str  # what its calibration is stored under ("" when no serial is known)
    note: str  # one sentence for the result, the run page and the certificate
    decision: str | None = None  # of a differing serial: trust-typed, refused, the operator's typed/identified/skip,
    # or "asked" while the operator's answer is awaited
    policy: str | None = None
    certify: bool = True  # False: refused, skipped or a duplicate (the reason is the note)

    def to_json(self) -> dict[str, Any]:
        """The identity as the run's result and the calibration's row keep it."""
        return {"typed_serial": self.typed, "identified_serial": self.identified, "identification": self.status,
                "serial_decision": self.decision, "serial_policy": self.policy, "serial_note": self.note}


def serial_prompt_text(slot: int, typed: str, identified: str | None, not_typed: str | None = None) -> str:
    """The operator prompt of a differing serial (or of a unit that reports none, typed as a serial whose
    unit reports its own): both serial numbers and the answers; ``not_typed``, why 'typed' will not
    certify it (the typed serial is another unit's), said before the answers."""
    taken = f" {not_typed[0].upper() + not_typed[1:]}: 'typed' would leave this unit uncalibrated." if not_typed else ""
    if identified is None:
        return (f"slot {slot}: the unit does not report a serial number, but unit {typed}, typed, reports its own "
                f"(calibrated before as {typed}).{taken} Answer 'typed' to certify it as {typed} (its calibration "
                f"becomes {typed}'s current one), or 'skip' to leave it uncalibrated")
    return (f"slot {slot}: the serial number typed is {typed} but the unit reports {identified}.{taken} "
            f"Answer 'typed' to certify it as {typed}, 'identified' to certify it as {identified}, "
            "or 'skip' to leave it uncalibrated")


@dataclass(frozen=True)
class _Checked(Procedure):
    """A procedure run with its units' identity check; its plan and reserve (for progress) are the
    procedure's own, since the check takes no table time and its prompts depend on the units mounted."""

    inner: Procedure | None = None

    def plan(self, params: Any) -> list[Any]:
        assert self.inner is not None
        return self.inner.plan(params)


@dataclass
class UnitCheck:
    """The identity check of one run's units, decided slot by slot before the table's first step
    (a batch unit's: its first after the mount prompt ``mounted_after``).

    ``idents`` None: the units are identified in the run (a batch's unit is mounted only after its
    prompt). ``seen``: serials already certified in the run's batch (identified serial -> which unit,
    e.g. "SN-A earlier in this batch (run 12)"). After the run, ``identities`` holds each slot's :class:`Identity`."""

    typed: dict[int, str]
    slots: list[int]
    policy: str = DEFAULT_POLICY
    idents: dict[int, tuple[str, str, str]] | None = None
    seen: dict[str, str] = field(default_factory=dict)
    #: serials units earlier in the run's batch were certified under -> which unit
    certified_before: dict[str, str] = field(default_factory=dict)
    #: the id of the prompt after which the units are mounted (a batch unit's), None when they are
    #: mounted before the run: the check waits for it (the table may go to its load pose before it)
    mounted_after: str | None = None
    identities: dict[int, Identity] = field(default_factory=dict)
    #: told each slot's identity once all are settled (before the table moves): the worker keeps them,
    #: so a run whose worker dies still names the units it measured
    on_settled: Callable[[dict[int, Identity]], None] | None = None
    #: whether a unit certified under a serial number reported it itself (the worker asks the database);
    #: None: nothing is known of earlier units
    reports_itself: Callable[[str], bool] | None = None
    done: bool = False
    #: serials certified in this run so far -> which unit (one serial is one unit, whoever typed it)
    certified: dict[str, str] = field(default_factory=dict)

    def procedure(self, proc: Procedure) -> Procedure:
        """``proc`` with the check in front of its first table step."""
        return _Checked(proc.name, proc.version, proc.params, lambda params: self._run(proc.run(params)), proc.doc,
                        proc.reserve, inner=proc)

    @property
    def nothing_left(self) -> bool:
        """Whether the check ended the run: no unit of the fixture may be certified."""
        return self.done and not any(i.certify for i in self.identities.values())

    def reasons(self) -> list[str]:
        """Why the units that will not be certified are not."""
        return [f"slot {i.slot}: {i.note}" for _, i in sorted(self.identities.items()) if not i.certify]

    def _run(self, gen: ProcedureGen) -> ProcedureGen:
        self.identities, self.done, self.certified = {}, False, dict(self.certified_before)
        mounting = self.mounted_after is not None
        reply: Reply = None
        while True:
            try:
                step = gen.send(reply)
            except StopIteration as stop:
                return stop.value
            if mounting and isinstance(step, Prompt) and step.id == self.mounted_after:
                mounting = False
                reply = yield step
                continue
            if not self.done and not mounting and isinstance(step, TIMED_STEPS):
                # the units are mounted now (any mount prompt is behind): name them before the table moves
                if self.idents is None:
                    got = yield Identify()
                    self.idents = dict(got) if isinstance(got, dict) else {}
                for slot in self.slots:
                    self.identities[slot] = yield from self._decide(slot)
                self.done = True
                if self.on_settled is not None:
                    self.on_settled(dict(self.identities))
                if self.nothing_left:  # nothing to calibrate: the table does not move for it
                    gen.close()
                    return Outcome(notes=self.reasons())
            reply = yield step

    def _decide(self, slot: int) -> Generator[Prompt, Reply, Identity]:
        out = yield from self._settle(slot)
        if not out.certify:
            return out
        if out.serial in self.certified:  # e.g. typed for one slot, and what another slot's unit reports
            # the facts of the note, without its "certified as" (it said "certified as SN-A2 ...; not certified")
            facts = re.split(r"[;:] certified as ", out.note)[0]
            return Identity(slot, out.typed, out.identified, "duplicate", out.serial,
                            f"{facts}; it would be certified as {out.serial}, but {self.certified[out.serial]} is "
                            "already certified as that: two units would be certified under one serial number; not "
                            "certified", out.decision, out.policy, certify=False)
        where = f"{out.serial} in slot {slot} of this run"
        self.certified[out.serial] = f"the unit in slot {slot} of this run"
        if out.identified:  # the physical unit, whatever it is certified as
            self.seen.setdefault(out.identified, where)
        return out

    def _settle(self, slot: int) -> Generator[Prompt, Reply, Identity]:
        """The slot's identity and decision, before the check against the serials certified so far."""
        typed = self.typed.get(slot)
        ident = (self.idents or {}).get(slot)
        identified = ident[1].strip() if ident and ident[1] and ident[1].strip() else None
        if identified is not None:
            try:
                check_serial(identified)
            except ValueError as e:  # a garbled answer, or one no URL /devices/{serial} reads back
                said = f"the unit reported {identified[:80]!r}, which is not a serial number ({e})"
                if typed is None:
                    return Identity(slot, None, identified, "not identified", "",
                                    f"{said}: not calibrated; start the run again with its serial number, e.g. "
                                    f'"serials": {{"{slot}": "SN-..."}}', certify=False)
                return Identity(slot, typed, identified, "not identified", typed, f"{said}; certified as the typed {typed}")
        if identified is None and typed is None:  # nothing to store its calibration under: do not move for it
            return Identity(slot, None, None, "not identified", "",
                            "the unit did not report a serial number and none was typed: not calibrated; start the "
                            f'run again with its serial number, e.g. "serials": {{"{slot}": "SN-..."}}', certify=False)
        if identified is None:
            assert typed is not None
            if self.reports_itself is not None and self.reports_itself(typed):
                return (yield from self._unidentified_known(slot, typed))
            return Identity(slot, typed, None, "not identified", typed,
                            f"the unit did not report a serial number (not identified); certified as the typed {typed}")
        if identified in self.seen:
            return Identity(slot, typed, identified, "duplicate", typed or identified,
                            f"the unit reports {identified}, already certified as {self.seen[identified]}: "
                            "the same physical unit mounted again; not certified", certify=False)
        if typed is None or typed == identified:
            out = Identity(slot, typed, identified, "identified", identified,
                           f"the unit reports {identified}" + (", as typed" if typed else ""))
        elif typed.lower() == identified.lower():  # one serial typed in another letter case: one unit, as it says
            out = Identity(slot, typed, identified, "identified", identified,
                           f"the unit reports {identified}, typed {typed} (letter case aside the same): certified as "
                           f"{identified}")
        else:
            out = yield from self._differs(slot, typed, identified)
        return out

    def _not_this_unit(self, slot: int, typed: str) -> str | None:
        """Why the unit in ``slot`` cannot be the typed serial's, or None: another slot's unit of this run
        reports it, or that unit reports its own (calibrated before as itself). Trusting the typed serial
        is for units whose own is wrong or unset (a shared factory default); filing this one under another
        unit's serial superseded that unit's current calibration without a word, and in a fixture of two
        swapped units certified the wrong one and left the real one uncalibrated."""
        other = next((s for s, ident in sorted((self.idents or {}).items())
                      if s != slot and ident and ident[1] and ident[1].strip() == typed), None)
        if other is not None:
            return f"unit {typed} is the one in slot {other} (it reports {typed})"
        if self.reports_itself is not None and self.reports_itself(typed):
            return (f"unit {typed} reports its own serial number (calibrated before as {typed}), so the unit on the "
                    f"fixture is not {typed}")
        return None

    def _ask(self, slot: int, typed: str, identified: str | None, status: str, facts: str,
             not_typed: str | None) -> Generator[Prompt, Reply, str]:
        """Ask the operator about the slot's serial (kept as "asked" meanwhile: a run aborted, or lost, at the
        prompt still says which unit was on the table); the answer, normalised. The prompt says why 'typed'
        would not certify the unit: the typed serial certified earlier in the run or its batch, else
        ``not_typed``."""
        taken = self.certified.get(typed)
        not_typed = f"{typed} is already certified for {taken}" if taken else not_typed
        self.identities[slot] = Identity(slot, typed, identified, status, typed, f"{facts}; the operator was asked",
                                         "asked", self.policy, certify=False)
        if self.on_settled is not None:
            self.on_settled(dict(self.identities))
        return normalise(str((yield Prompt(serial_prompt_text(slot, typed, identified, not_typed),
                                           id=f"{PROMPT_PREFIX}{slot}")) or ""))

    def _unidentified_known(self, slot: int, typed: str) -> Generator[Prompt, Reply, Identity]:
        """A unit that reports no serial number, typed as one whose unit reports its own: settled by the
        policy as a differing serial is (refuse: not calibrated; trust-typed: certified, said; prompt: the
        operator answers 'typed' or 'skip')."""
        facts = (f"the unit did not report a serial number (not identified), but unit {typed}, typed, reports its "
                 f"own (calibrated before as {typed})")
        policy = self.policy
        if policy == "trust-typed":
            return Identity(slot, typed, None, "not identified", typed,
                            f"{facts}; certified as {typed} (serial policy trust-typed)", "trust-typed", policy)
        if policy == "refuse":
            return Identity(slot, typed, None, "not identified", typed,
                            f"{facts}; refused (serial policy refuse): mount unit {typed} and check that it answers "
                            "the ID command, or start the run with this unit's own serial number", "refused", policy,
                            certify=False)
        answer = yield from self._ask(slot, typed, None, "not identified", facts, None)
        if answer == "typed":
            return Identity(slot, typed, None, "not identified", typed,
                            f"{facts}; certified as {typed} on the operator's answer", "typed", policy)
        return self._skipped(slot, typed, None, "not identified", facts, answer)

    def _differs(self, slot: int, typed: str, identified: str) -> Generator[Prompt, Reply, Identity]:
        both = f"the serial number typed is {typed} but the unit reports {identified}"
        policy = self.policy
        not_typed = self._not_this_unit(slot, typed)
        if policy == "trust-typed":
            if not_typed:
                return Identity(slot, typed, identified, "differs", typed,
                                f"{both}; refused although the serial policy is trust-typed: {not_typed}; mount unit "
                                f"{typed}, or start the run with serial {identified}", "refused", policy, certify=False)
            return Identity(slot, typed, identified, "differs", typed,
                            f"{both}; certified as {typed} (serial policy trust-typed)", "trust-typed", policy)
        if policy == "refuse":
            return Identity(slot, typed, identified, "differs", typed,
                            f"{both}; refused (serial policy refuse): mount unit {typed}, or start the run with "
                            f"serial {identified}", "refused", policy, certify=False)
        answer = yield from self._ask(slot, typed, identified, "differs", both, not_typed)
        # (a serial certified earlier in the run or its batch: a 'typed' answer is found a duplicate, `_decide`)
        if answer == "typed" and not_typed and typed not in self.certified:
            return Identity(slot, typed, identified, "differs", typed,
                            f"{both}; the operator answered 'typed', but {not_typed}: not certified", "typed", policy,
                            certify=False)
        if answer == "typed":
            return Identity(slot, typed, identified, "differs", typed,
                            f"{both}; certified as {typed} on the operator's answer", "typed", policy)
        if answer == "identified":
            return Identity(slot, typed, identified, "differs", identified,
                            f"{both}; certified as {identified} on the operator's answer", "identified", policy)
        return self._skipped(slot, typed, identified, "differs", both, answer)

    def _skipped(self, slot: int, typed: str, identified: str | None, status: str, facts: str, answer: str) -> Identity:
        """The slot left uncalibrated on the operator's 'skip' (or an answer not understood)."""
        why = "skipped by the operator" if answer == "skip" else f"answer {answer!r} not understood"
        return Identity(slot, typed, identified, status, typed, f"{facts}; {why}: not certified", "skip", self.policy,
                        certify=False)


__all__ = ["SerialPolicy", "POLICIES", "DEFAULT_POLICY", "CHOICES", "Identity", "UnitCheck", "is_serial_prompt",
           "normalise", "serial_prompt_text"]
