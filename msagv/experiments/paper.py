"""The paper's result tables (Section 4.4, Tables 1-3), transcribed from its LaTeX source.

Columns in the paper's order: Omega, W_tw [J], W_alpha [J], W_s [J], W_t [J], e_bar,
e_x [cm], e_y [cm], e_phi [deg]. Row groups are the paper's: speeds for Case 1 (35, 25, 15,
5 km/h), 10 km/h for Case 2, loads for Case 3 (8, 12, 16, 20 t at 30 km/h). The numbers were
extracted from the ``tabular`` environments by a script and are kept here as literals, so
``docs/RESULTS.md`` can be regenerated without the paper's source.

Checked against the paper's own definitions (eq. 31-33, in tests/test_experiments.py): every
row satisfies W_tw = W_s + W_alpha + W_t, e_bar = (e_x + e_y + e_phi) / 3 and eq. (33) to
within the printed rounding, except Case 1, 25 km/h, Kinematic, whose Omega is printed as
3.31e5 while eq. (33) with its W_tw and e_bar gives 4.11e5. Case 3's text quotes the 8 t
rows as "12 Tons" (NTWO 8.80e8 J, e_bar 4.83; TWO Omega 3.40e4). Rows are kept as printed.
"""

from __future__ import annotations

PAPER_COLUMNS = ("Omega", "W_tw", "W_alpha", "W_s", "W_t", "e_bar", "e_x_cm", "e_y_cm",
                 "e_phi_deg")

# (group, method, (Omega, W_tw, W_alpha, W_s, W_t, e_bar, e_x, e_y, e_phi))
_ROWS = [
    # Table 1 (Case 1, 12 t)
    ('35 km/h', 'Kinematic', (3.73e5, 3.16e8, 8.98e7, 1.45e8, 8.04e7, 440.77, 906.76, 354.23, 61.31)),
    ('35 km/h', 'DH', (4.81e4, 1.07e9, 3.01e8, 7.56e8, 7.97e6, 48.74, 55.50, 50.86, 39.85)),
    ('35 km/h', 'TCT', (6.82e4, 2.20e9, 2.68e8, 1.93e9, 7.79e6, 42.40, 43.26, 55.40, 28.54)),
    ('35 km/h', 'NTWO', (3.79e4, 9.12e8, 2.12e8, 6.92e8, 7.51e6, 9.60, 12.10, 8.68, 8.03)),
    ('35 km/h', 'TWO', (3.63e4, 7.37e8, 2.27e8, 5.03e8, 7.59e6, 18.44, 9.58, 27.51, 18.23)),
    ('25 km/h', 'Kinematic', (3.31e5, 5.82e8, 1.38e8, 2.36e8, 2.08e8, 290.47, 568.62, 245.02, 57.79)),
    ('25 km/h', 'DH', (5.38e4, 1.96e9, 4.35e8, 1.51e9, 1.57e7, 7.20, 10.36, 7.75, 3.49)),
    ('25 km/h', 'TCT', (4.44e4, 1.18e9, 4.61e8, 7.02e8, 1.54e7, 13.89, 26.31, 14.01, 1.36)),
    ('25 km/h', 'NTWO', (3.98e4, 1.53e9, 2.00e8, 1.32e9, 1.53e7, 1.22, 1.66, 1.26, 0.74)),
    ('25 km/h', 'TWO', (3.46e4, 1.01e9, 1.76e8, 8.19e8, 1.49e7, 2.52, 3.04, 2.27, 2.25)),
    ('15 km/h', 'Kinematic', (4.03e5, 1.69e9, 3.04e8, 6.32e8, 7.56e8, 95.74, 156.65, 90.96, 39.62)),
    ('15 km/h', 'DH', (9.06e4, 5.47e9, 8.21e8, 4.60e9, 4.25e7, 7.68, 10.26, 9.21, 3.55)),
    ('15 km/h', 'TCT', (1.24e5, 9.04e9, 5.48e8, 8.45e9, 4.22e7, 14.05, 26.57, 14.39, 1.18)),
    ('15 km/h', 'NTWO', (7.04e4, 5.45e9, 8.46e8, 4.56e9, 4.28e7, 0.62, 0.62, 0.68, 0.57)),
    ('15 km/h', 'TWO', (5.33e4, 2.42e9, 3.64e8, 2.02e9, 4.10e7, 2.24, 2.63, 1.97, 2.11)),
    ('5 km/h', 'Kinematic', (9.83e5, 1.76e10, 1.66e9, 3.76e9, 1.22e10, 54.92, 90.11, 51.97, 22.70)),
    ('5 km/h', 'DH', (3.05e5, 5.12e10, 2.58e9, 4.83e10, 3.82e8, 20.03, 31.57, 17.23, 11.30)),
    ('5 km/h', 'TCT', (9.98e6, 8.30e11, 1.91e9, 8.28e11, 3.78e8, 120.01, 224.44, 116.25, 19.33)),
    ('5 km/h', 'NTWO', (2.43e5, 4.86e10, 2.87e9, 4.56e10, 1.87e8, 2.59, 3.41, 2.90, 1.46)),
    ('5 km/h', 'TWO', (2.00e5, 3.17e10, 2.66e9, 2.88e10, 1.88e8, 3.25, 2.81, 3.00, 3.94)),
    # Table 2 (Case 2, 12 t, 60 deg initial heading error)
    ('10 km/h', 'Kinematic', (7.29e5, 4.77e9, 2.24e8, 5.82e8, 3.96e9, 111.49, 189.59, 92.23, 52.66)),
    ('10 km/h', 'DH', (6.39e4, 1.99e9, 4.14e8, 1.55e9, 2.58e7, 36.33, 20.34, 41.09, 47.55)),
    ('10 km/h', 'TCT', (6.44e4, 1.94e9, 7.80e7, 1.86e9, 4.54e6, 44.41, 57.83, 34.26, 41.15)),
    ('10 km/h', 'NTWO', (5.96e4, 1.84e9, 2.44e8, 1.57e9, 2.55e7, 27.09, 9.73, 27.95, 43.60)),
    ('10 km/h', 'TWO', (5.71e4, 1.66e9, 3.07e8, 1.33e9, 2.50e7, 29.23, 12.74, 29.36, 45.59)),
    # Table 3 (Case 3, 30 km/h)
    ('8 t', 'Kinematic', (3.22e5, 2.71e8, 7.28e7, 1.15e8, 8.34e7, 382.21, 779.11, 307.33, 60.19)),
    ('8 t', 'DH', (4.09e4, 8.97e8, 2.21e8, 6.69e8, 7.12e6, 22.43, 27.36, 28.21, 11.72)),
    ('8 t', 'TCT', (3.67e4, 7.57e8, 2.25e8, 5.23e8, 9.06e6, 17.93, 27.47, 13.18, 13.15)),
    ('8 t', 'NTWO', (3.47e4, 8.80e8, 1.50e8, 7.21e8, 8.13e6, 4.83, 4.89, 6.07, 3.51)),
    ('8 t', 'TWO', (3.40e4, 7.06e8, 1.38e8, 5.61e8, 7.02e6, 11.74, 16.29, 11.39, 7.53)),
    ('12 t', 'Kinematic', (3.91e5, 4.09e8, 1.06e8, 1.80e8, 1.23e8, 373.11, 755.26, 304.39, 59.69)),
    ('12 t', 'DH', (4.64e4, 1.32e9, 2.98e8, 1.01e9, 1.08e7, 11.85, 17.48, 12.64, 5.43)),
    ('12 t', 'TCT', (4.64e4, 1.27e9, 8.37e8, 4.09e8, 2.88e7, 13.77, 26.29, 13.63, 1.39)),
    ('12 t', 'NTWO', (4.01e4, 1.15e9, 2.06e8, 9.39e8, 9.81e6, 5.28, 6.64, 4.43, 4.78)),
    ('12 t', 'TWO', (3.78e4, 9.33e8, 1.76e8, 7.47e8, 9.66e6, 8.51, 12.84, 7.70, 4.99)),
    ('16 t', 'Kinematic', (4.57e5, 5.48e8, 1.38e8, 2.43e8, 1.67e8, 381.61, 763.45, 320.23, 61.13)),
    ('16 t', 'DH', (4.91e4, 1.67e9, 3.39e8, 1.32e9, 1.44e7, 6.29, 7.40, 8.39, 3.07)),
    ('16 t', 'TCT', (6.34e4, 2.35e9, 3.80e8, 1.96e9, 1.37e7, 14.61, 26.65, 13.29, 3.88)),
    ('16 t', 'NTWO', (4.08e4, 1.58e9, 2.65e8, 1.30e9, 1.40e7, 1.32, 1.65, 1.49, 0.80)),
    ('16 t', 'TWO', (3.69e4, 1.04e9, 2.27e8, 8.00e8, 1.39e7, 3.88, 3.93, 3.44, 4.26)),
    ('20 t', 'Kinematic', (5.01e5, 6.69e8, 1.67e8, 2.96e8, 2.06e8, 375.87, 743.45, 322.39, 61.77)),
    ('20 t', 'DH', (5.88e4, 2.35e9, 5.43e8, 1.79e9, 1.79e7, 6.83, 9.28, 7.45, 3.77)),
    ('20 t', 'TCT', (8.06e4, 3.79e9, 5.37e8, 3.23e9, 1.69e7, 14.94, 25.98, 14.14, 4.69)),
    ('20 t', 'NTWO', (4.57e4, 2.10e9, 3.56e8, 1.72e9, 1.76e7, 0.98, 1.33, 1.05, 0.57)),
    ('20 t', 'TWO', (4.32e4, 1.33e9, 3.40e8, 9.72e8, 1.79e7, 5.40, 5.63, 4.40, 6.18)),
]

PAPER_CASE = {"case1": "Table 1", "case2": "Table 2", "case3": "Table 3"}
_GROUPS = {
    "case1": ("35 km/h", "25 km/h", "15 km/h", "5 km/h"),
    "case2": ("10 km/h",),
    "case3": ("8 t", "12 t", "16 t", "20 t"),
}


def paper_table(case: str) -> dict[tuple[str, str], dict[str, float]]:
    """The paper's rows of ``case`` ('case1' | 'case2' | 'case3'):
    ``{(group, method): {column: value}}``."""
    if case not in _GROUPS:
        raise KeyError(f"the paper has no table for '{case}'")
    groups = _GROUPS[case]
    return {(g, m): dict(zip(PAPER_COLUMNS, v)) for g, m, v in _ROWS if g in groups}
