"""A run's settings and plan together, changed by name: how the tests name a tiny variant of a preset."""

from __future__ import annotations

from dataclasses import dataclass

from dresg_addon.method.config import Plan, StylizeConfig, preset_run


@dataclass(frozen=True)
class Variant:
    config: StylizeConfig
    plan: Plan

    @classmethod
    def of(cls, name: str, **changes) -> Variant:
        return cls(*preset_run(name, **changes))

    def with_(self, **changes) -> Variant:
        config, plan = preset_run(self.config.preset)  # which names are the plan's
        plan_names = set(vars(plan)) | set(vars(plan.ablation))
        settings = {k: v for k, v in changes.items() if k not in plan_names}
        steps = {k: v for k, v in changes.items() if k in plan_names}
        return Variant(self.config.with_(**settings), self.plan.with_(**steps))
