"""Map points of floors, walls, tables and upside-down cameras for the floor and scale tests
(test/core/test_floor.py, test/core/test_scale.py)."""

from __future__ import annotations

import math

import numpy as np


def rot_x(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])


def rot_z(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])


def scene(height: float, pitch_deg: float, roll_deg: float, n_floor: int, n_clutter: int, noise: float,
           seed: int = 0) -> np.ndarray:
    """Points in a camera frame pitched down by pitch_deg and rolled by roll_deg, at height above a floor
    (level frame: x right, y down, z forward; floor y = height), plus a wall and boxes above the floor."""
    rng = np.random.default_rng(seed)
    floor = np.column_stack([rng.uniform(-3, 3, n_floor), np.full(n_floor, height), rng.uniform(1.0, 8.0, n_floor)])
    wall = np.column_stack([rng.uniform(-3, 3, n_clutter), rng.uniform(-2, height - 0.3, n_clutter),
                            np.full(n_clutter, 9.0)])
    box = np.column_stack([np.full(n_clutter, 1.5), rng.uniform(0.2 * height, 0.7 * height, n_clutter),
                           rng.uniform(2, 6, n_clutter)])
    X_level = np.vstack([floor, wall, box])
    X_level += rng.normal(0, noise, X_level.shape)
    # The camera is pitched down: a level point X is seen at R X with R the inverse camera rotation.
    R_cam = rot_x(-pitch_deg) @ rot_z(roll_deg)  # camera axes in the level frame
    return X_level @ R_cam  # = (R_cam^T X^T)^T


def upside_down_scene(height: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A camera mounted upside down (rolled 180 deg, pitched 15 deg down), ``height`` above the floor of a
    corridor, as a 640 x 480 image (f = 500 px) sees it: the floor and both side walls. Returns the points in
    the camera frame and the true up (from the floor towards the camera) in that frame."""
    rng = np.random.default_rng(seed)
    floor = np.column_stack([rng.uniform(-2.5, 2.5, 80), np.full(80, height), rng.uniform(1.0, 8.0, 80)])
    walls = np.column_stack([rng.choice([-3.0, 3.0], 300), rng.uniform(-20 * height, -0.5 * height, 300),
                             rng.uniform(1.0, 9.0, 300)])
    X_level = np.vstack([floor, walls]) + rng.normal(0.0, 0.001 * height, (380, 3))
    R_cam = rot_x(-15.0) @ rot_z(180.0)  # camera axes in the level frame (x right, y down, z forward)
    X = X_level @ R_cam
    seen = (X[:, 2] > 0.1) & (np.abs(X[:, 0]) < 0.64 * X[:, 2]) & (np.abs(X[:, 1]) < 0.48 * X[:, 2])
    return X[seen], R_cam.T @ np.array([0.0, -1.0, 0.0])


def table_over_its_pedestal(height: float) -> np.ndarray:
    """A level camera ``height`` above a round table top (12 points, 1.6 m wide, 5 m ahead) whose pedestal
    (30 points) goes down 5-9 heights beneath it, and no floor in view: a horizontal plane with the scene
    beneath it, the only plane below the camera within 35 deg of level (the ground-robot bag rotated by 180
    deg had such planes among 1-4 candidates and took them for its floor: metres 3.3x too large)."""
    a = np.linspace(0.0, 2.0 * np.pi, 12, endpoint=False)
    top = np.column_stack([0.8 * np.cos(a), np.full(12, height), 5.0 + 0.8 * np.sin(a)])
    pedestal = np.column_stack([np.zeros(30), height * np.linspace(6.0, 10.0, 30), np.full(30, 5.0)])
    return np.vstack([top, pedestal])
