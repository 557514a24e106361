"""Identification: SIDBE, the joint estimator, IDIM-LS, and the choice among them (:mod:`.auto`)."""
