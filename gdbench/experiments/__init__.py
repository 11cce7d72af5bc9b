"""The experiment: sweeps of cells (``sweep``), their tables (``tables``) and the paper's claims
as verdicts (``claims``)."""
