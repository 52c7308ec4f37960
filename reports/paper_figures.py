"""Figures published in the paper (Tang et al.), to print beside ours.

Table 1: triangles in the scene, triangle references held by the naive and the
local-branch ("Our") tree, and 512x512 4 spp frame times in seconds. Our scenes stand
in for the paper's: cbox-sphere for CBox, car (dragon in the red box) for Car, the
samurai monastery for Room, the Crytek Sponza for Sponza.
"""

from __future__ import annotations

TABLE1 = {
    "cbox-sphere": {"paper_scene": "CBox", "triangles": 2188, "naive_references": 12440, "local_references": 9073,
                    "naive_frame_seconds": 18.99, "local_frame_seconds": 16.57},
    "car": {"paper_scene": "Car", "triangles": 10264, "naive_references": 97248, "local_references": 67293,
            "naive_frame_seconds": 30.61, "local_frame_seconds": 22.31},
    "samurai-monastery": {"paper_scene": "Room", "triangles": 340265, "naive_references": 2619894,
                          "local_references": 1738934, "naive_frame_seconds": 274.09, "local_frame_seconds": 165.76},
    "crytek-sponza": {"paper_scene": "Sponza", "triangles": 262267, "naive_references": 1739676,
                      "local_references": 1206221, "naive_frame_seconds": 373.90, "local_frame_seconds": 285.91},
}
