"""Simulation worlds other than simfleet's own (:mod:`simfleet.sim`): the estimators were shaped on
that one, so accuracy and coverage are checked on worlds that differ where real data differ."""
