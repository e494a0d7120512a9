"""Algorithm 1 of the paper on SUMO's clock: CRCHFL, HFL and SFL as sequences of one loop's steps.

``Federation.step`` copies the state, applies the stopping rules (``cloud_rounds`` reached; the rest of
the budget cannot carry one more model transfer), asks the scheme's steps (federation/scheme_steps.py:
the step protocol, ``steps_for``) which step comes next, runs it with the shared services
(federation/services.py: the clock's transfers and their charges, training, evaluation), then appends
the step's ledger records and counts the step. docs/federation.md maps Algorithm 1 onto the steps line
by line.

The loop's whole memory is a ``FederationState`` (models, times, counters;
the ledger records and metric lines it appends to are history it never reads
back), so a checkpoint is the state and a resume continues from it. Mobility
and training are injected (a ``Clock`` and a ``Trainer``), so the loop runs
with scripted tracks and tiny models in tests.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

from crchfl_sumo.accounting.ledger import Ledger
from crchfl_sumo.data.samples import Samples
from crchfl_sumo.federation.scheme_steps import StepSequence, steps_for
from crchfl_sumo.federation.services import StepServices
from crchfl_sumo.federation.state import FederationState, Labeller, LoopInputs, Trainer
from crchfl_sumo.links.clock import Clock


class Federation:
    """Runs the loop of one setup on a clock with a trainer; ``step`` advances one step of the scheme.

    ``data`` and ``labeller``: as ``StepServices`` takes them (the vehicles' samples over time; [dagger]'s
    route experts). ``steps``: the scheme's steps (default: ``steps_for(setup.config)``: the built-in ones,
    or ``[federation] scheme_steps``).
    """

    def __init__(
        self, setup: LoopInputs, clock: Clock, trainer: Trainer, data: Callable[[str, float], Samples] | None = None,
        labeller: Labeller | None = None, steps: StepSequence | None = None,
    ) -> None:
        self.setup = setup
        self.services = StepServices(setup, clock, trainer, data, labeller)
        self.steps = steps or steps_for(setup.config)

    def run(self, state: FederationState, on_step: Callable[[FederationState], None] | None = None) -> FederationState:
        """Step until the stopping rule; ``on_step`` sees the state after every step (checkpoints, progress)."""
        while not state.done:
            state = self.step(state)
            if on_step is not None:
                on_step(state)
        return state

    def step(self, state: FederationState) -> FederationState:
        """One step on a copy of ``state``: the one the scheme's steps name next (stage I, one edge
        aggregation (+ cloud), one SFL round, or one asynchronous event)."""
        state = dataclasses.replace(
            state,
            vehicle_models=dict(state.vehicle_models),
            edge_models=dict(state.edge_models),
            edge_weights=dict(state.edge_weights),
            member=dict(state.member),
            ready_s=dict(state.ready_s),
            open_s=dict(state.open_s),
            records=list(state.records),
            metrics=list(state.metrics),
            stragglers=list(state.stragglers),
            transfers=dict(state.transfers),
            residuals=dict(state.residuals),
        )
        ledger = Ledger(self.setup.sizes, byte_totals=state.ledger_totals)
        hyper = self.setup.hyper
        self.services.start_step()
        if hyper.cloud_rounds and state.cloud_rounds >= hyper.cloud_rounds:
            state.stop_reason = "cloud_rounds"
        elif not ledger.can_carry_model():
            state.stop_reason = "budget"
        else:
            self.steps.next_step(state).run(self.services, state, ledger)
        charged = ledger.records  # this step's
        state.records.extend(charged)
        state.ledger_totals = ledger.byte_totals()
        state.transfers_end_s = max([state.transfers_end_s, *(r.end_s for r in charged)])
        state.steps += 1
        return state
