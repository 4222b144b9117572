"""``GET /v1/labels``: the semantic label set."""

from __future__ import annotations

from fastapi import APIRouter

from fusion.labels import LABELS
from service.api.deps import AnyRole
from service.api.problems import problem_responses
from service.api.schemas import Label

router = APIRouter(prefix="/v1/labels", tags=["labels"])


@router.get("", operation_id="listLabels", response_model=list[Label], responses=problem_responses(401, 403))
def list_labels(_principal: AnyRole) -> list[Label]:
    """The label set; ids are fixed (0 = unlabeled, ignored in training and evaluation)."""
    return [Label(id=label.id, name=label.name, color=list(label.color)) for label in LABELS]
