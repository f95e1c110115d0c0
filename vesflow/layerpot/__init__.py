"""Stokes layer potentials: singular (self), near-singular and far-field quadrature (method reference, section 5)."""
