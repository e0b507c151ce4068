"""Everything fixed about one bridge's estimation (window, basis, design beam, deck, element model), and its
passes whitened against their leave-one-out consensus."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

from shared.fe.beam import Beam
from shared.fe.design import design_beam
from shared.registry import Bridge

from cloud.bridge.basis import SpanBasis
from cloud.bridge.passdata import PassData, Reference, Window
from cloud.bridge.stiffness import BearingElementModel, ElementModel, StiffnessPrior
from cloud.bridge.whitening import WhitenedPass, whiten_pass


@dataclasses.dataclass(frozen=True)
class Setup:
    """Everything fixed about one bridge's estimation: window, basis, design beam, deck model."""

    bridge: Bridge
    window: Window
    basis: SpanBasis
    beam: Beam
    deck: str = "smooth"

    @classmethod
    def of(cls, bridge: Bridge, deck: str = "smooth", spacing_m: float = 0.05, pre_m: float = 60.0,
           post_m: float = 25.0) -> "Setup":
        window = Window.of(bridge, spacing_m, pre_m, post_m)
        basis = SpanBasis.of(window, bridge.n_elements)
        return cls(bridge, window, basis, design_beam(bridge), deck)

    def model(self, prior: StiffnessPrior = StiffnessPrior()) -> "ElementModel | BearingElementModel":
        """The per-element model the registry calls for: bearings when ``supports`` says so."""
        if self.bridge.supports == "rotational_springs":
            k0 = 8.0 if self.bridge.krot_nm_per_rad is None else math.log10(max(self.bridge.krot_nm_per_rad, 1.0))
            # The departure scale is not learnt here: each of the bearing model's fits costs a finite-
            # difference Jacobian (n + 2 FE solves) per Newton step, and the grid would multiply that by
            # nine for the same Krot and mean stiffness.
            return BearingElementModel(self.basis, self.bridge, dataclasses.replace(prior, scales=()), (k0, 2.5))
        if self.deck == "rough":
            # Nor on a rough deck: what of the deck profile the weights' spread leaves unseparated is
            # smooth along the span, reads as departures, and the evidence would loosen the prior until
            # the bump is fitted as stiffness.
            prior = dataclasses.replace(prior, scales=())
        return ElementModel.of(self.basis, self.beam, prior)


def whiten_all(passes: Sequence[PassData], setup: Setup) -> list[WhitenedPass]:
    """Whiten every pass against the leave-one-out consensus of the others."""
    ref = Reference.of(passes)
    return [whiten_pass(p, ref, setup.basis, setup.deck) for p in passes]
