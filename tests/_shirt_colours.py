"""The ten RGB albedos (0-255) of the procedural shirt used by the colour tests."""

import numpy as np

SHIRT = np.array(
    [
        [205, 35, 40],
        [35, 170, 50],
        [40, 60, 205],
        [225, 210, 40],
        [40, 190, 200],
        [200, 45, 190],
        [235, 125, 30],
        [110, 45, 170],
        [150, 225, 60],
        [245, 140, 170],
    ],
    float,
)
