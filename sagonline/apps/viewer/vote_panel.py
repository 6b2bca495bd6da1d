"""The viewer's vote controls, generated from each vote method's settings dataclass
(`vote.settings`, through `vote_setting_specs`): a method dropdown, one control
per setting (a number, a choice, or an on/off box beside a number for a setting that can be
off), each enabled only while the chosen method reads it, and the body rule."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from sagonline.vote.settings import SELECTION, VoteConfig, field_docs, vote_setting_specs


class VotePanel:
    """Controls for a `VoteConfig`: `config()` reads them back (the settings its method does not
    read keep their defaults; which masks vote is kept from `current`)."""

    def __init__(self, gui, current: VoteConfig, on_change: Callable[[], None]):
        from sagonline.core.plugins import VOTE_RULES

        self.specs = vote_setting_specs()
        self.current = current
        self.method = gui.add_dropdown(
            "vote method", list(VOTE_RULES.keys()), initial_value=current.method
        )
        self.inputs: dict[str, Any] = {}
        self.off: dict[str, Any] = {}  # name -> its on/off box (settings that can be off)
        for spec in self.specs:
            value = getattr(current, spec.name)
            if spec.optional:
                self.off[spec.name] = gui.add_checkbox(
                    f"{spec.name} on", value is not None, hint=spec.doc
                )
            self.inputs[spec.name] = control(gui, spec, spec.default if value is None else value)
        self.inputs["body"] = gui.add_checkbox(
            "keep each object's body", current.body, hint=field_doc("body")
        )
        for handle in [self.method, *self.inputs.values(), *self.off.values()]:
            handle.on_update(lambda _: on_change())
        self.enable()

    def enable(self) -> None:
        """Enable the controls of the settings the chosen method reads, disable the others."""
        method = str(self.method.value)
        for spec in self.specs:
            reads = method in spec.readers
            self.inputs[spec.name].disabled = not reads
            if spec.name in self.off:
                self.off[spec.name].disabled = not reads

    def config(self) -> VoteConfig:
        """The controls as a VoteConfig (a value out of range is refused by it)."""
        self.enable()
        method = str(self.method.value)
        values: dict[str, Any] = {k: getattr(self.current, k) for k in SELECTION}
        values |= {"method": method, "body": bool(self.inputs["body"].value)}
        for spec in self.specs:
            if method not in spec.readers:
                continue
            value = spec.kind(self.inputs[spec.name].value)
            off = spec.name in self.off and not self.off[spec.name].value
            values[spec.name] = None if off else value
        self.current = VoteConfig(**values)
        return self.current


def control(gui, spec, value):
    """One setting's control: a dropdown for choices, a checkbox for a bool, else a number with
    the setting's bounds and step."""
    if spec.choices:
        return gui.add_dropdown(spec.name, spec.choices, initial_value=value, hint=spec.doc)
    if spec.kind is bool:
        return gui.add_checkbox(spec.name, bool(value), hint=spec.doc)
    step = spec.step or (1 if spec.kind is int else 0.01)
    return gui.add_number(spec.name, value, min=spec.low, max=spec.high, step=step, hint=spec.doc)


def field_doc(name: str) -> str:
    """A VoteConfig field's documentation, as one line."""
    return field_docs(VoteConfig).get(name, "")
