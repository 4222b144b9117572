"""The semantic label set (API.md). Ids are fixed; deployments may append, never renumber."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Label:
    id: int
    name: str
    color: tuple[int, int, int]


# the label table: one declarative row per class (the rows' like shapes are deliberate; duplicates)
LABELS: tuple[Label, ...] = (
    Label(0, "unlabeled", (0, 0, 0)),
    Label(1, "road", (128, 64, 128)),
    Label(2, "sidewalk", (244, 35, 232)),
    Label(3, "lane_marking", (255, 255, 255)),
    Label(4, "terrain", (152, 251, 152)),
    Label(5, "building", (70, 70, 70)),
    Label(6, "fence", (190, 153, 153)),
    Label(7, "pole", (153, 153, 153)),
    Label(8, "traffic_sign", (220, 220, 0)),
    Label(9, "vegetation", (107, 142, 35)),
    Label(10, "vehicle", (0, 0, 142)),
    Label(11, "obstacle", (255, 0, 0)),
)

UNLABELED = 0
NUM_CLASSES = len(LABELS)
LABEL_BY_NAME = {label.name: label for label in LABELS}
COLOR_TO_LABEL = {label.color: label.id for label in LABELS}

