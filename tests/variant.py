"""A run's settings and plan together, changed by name: how the tests name a tiny variant of a preset."""

from __future__ import annotations

from dataclasses import dataclass, fields

from dresg_addon.method.config import Ablation, Plan, StylizeConfig, preset_run


@dataclass(frozen=True)
class Variant:
    config: StylizeConfig
    plan: Plan

    @classmethod
    def of(cls, name: str, **changes) -> Variant:
        return cls(*preset_run(name, **changes))

    def with_(self, **changes) -> Variant:
        plan_names = {f.name for f in fields(Plan)} | {f.name for f in fields(Ablation)}
        settings = {k: v for k, v in changes.items() if k not in plan_names}
        steps = {k: v for k, v in changes.items() if k in plan_names}
        return Variant(self.config.with_(**settings), self.plan.with_(**steps))
