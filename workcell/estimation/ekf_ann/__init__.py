"""Online EKF-ANN (seed 004, Horvath & Neuner): kinematic model in the system equation, a small
network for the non-geometric part in the observation equation; JAX filter fast enough to run live.
"""
