"""Stokes layer potentials: singular (self), near-singular and far-field quadrature (docs/explanation/method.md, section 5)."""
