"""SO(3) / SE(3) helpers, vectorised over a leading axis (see :mod:`.so3`, :mod:`.se3`)."""
