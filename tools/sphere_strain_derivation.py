"""Derivation (sympy) of the l = 2 velocity of an inextensible spherical membrane, docs/explanation/dynamics.md.

Sphere of radius 1, outer viscosity 1, inner lambda; Lamb's solution inside (n = 2) and outside
(n = -3, plus the far field E.x); the membrane velocity A Y n + (A/3) grad_s Y, Y = n.E.n, is
surface-divergence free (div_s(u_n n) = 2 u_n on the unit sphere, lap_s Y = -6 Y); the traction
jump balances the tension force grad_s s - 2 s n (s = s2 Y) plus an external normal force F Y n.
Solves the four velocity matching conditions and the two force balances at sample points.

    python3 tools/sphere_strain_derivation.py     (needs sympy; not part of the run environment)

prints   strain (F = 0):       A = 60/(23 lambda + 32)
         normal force (E = 0): A = 6/(23 lambda + 32)   (per unit F)
"""
import random

import sympy as sp

x, y, z, lam = sp.symbols("x y z lambda", real=True)
A, s, Pi, Fi, Po, Fo = sp.symbols("A s Pi Fi Po Fo")
X = sp.Matrix([x, y, z])
r2 = x * x + y * y + z * z
r = sp.sqrt(r2)
E = sp.diag(-1, sp.Rational(1, 2), sp.Rational(1, 2))
Q = (X.T * E * X)[0]
n = X / r
Y = Q / r2


def grad(f):
    return sp.Matrix([sp.diff(f, v) for v in (x, y, z)])


def traction(u, p, mu):
    J = sp.Matrix(3, 3, lambda i, j: sp.diff(u[i], [x, y, z][j]))
    return (-p * sp.eye(3) + mu * (J + J.T)) * n


def solve(far_field, F):
    p_in, p_out = Pi * Q, Po * Q / r ** 5
    u_in = (sp.Rational(5, 42) * r2 * grad(p_in) - sp.Rational(2, 21) * X * p_in) / lam + grad(Fi * Q)
    u_out = far_field * E * X + sp.Rational(1, 2) * X * p_out + grad(Fo * Q / r ** 5)
    u_membrane = A * Y * n + A / 3 * 2 * (E * n - Y * n)
    f_tension = s * 2 * (E * n - Y * n) - 2 * s * Y * n
    balance = traction(u_out, p_out, 1) - traction(u_in, p_in, lam) + f_tension + F * Y * n
    random.seed(1)
    eqs = []
    for _ in range(4):
        v = [sp.Rational(random.randint(-9, 9), 7) for _ in range(3)]
        nv = sp.sqrt(sum(t * t for t in v))
        pt = {x: v[0] / nv, y: v[1] / nv, z: v[2] / nv}
        eqs += [sp.simplify(e.subs(pt)) for e in list(u_in - u_membrane) + list(u_out - u_membrane) + list(balance)]
    return sp.factor(sp.solve(eqs, [A, s, Pi, Fi, Po, Fo], dict=True)[0][A])


print("strain (F = 0):       A =", solve(1, 0))
print("normal force (E = 0): A =", solve(0, 1), " (per unit F)")
