"""The seed report's robot as RobotParams keyword arguments: Table 5.1 (the nominal robot) and
Table 5.2 (the same with a 2 kg mass off centre), for the model, plant and backend tests."""

from __future__ import annotations

TABLE_5_1 = dict(
    H=0.115, L=0.108, R=0.108, r_L=0.049, r_R=0.051, r_3=0.052, d_xc=0.026, d_yc=0.0,
    m_p=0.8, m_L=1.2, m_R=1.2, m_3=0.6, I_p=6.43e-3, I_L=3.5e-4, I_R=3.5e-4, I_3=6.55e-4,
    I_wL=6.29e-4, I_wR=6.29e-4, I_w3=6.29e-4,
)
TABLE_5_2 = dict(TABLE_5_1, d_xc=0.056, d_yc=0.010, m_p=2.8)
