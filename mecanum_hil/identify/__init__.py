"""Identification: model coefficients and effect parameters from recordings (pure)."""
