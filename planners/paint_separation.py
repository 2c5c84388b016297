"""What the cell found about the paint on a piece (planners.paint_color fits it): sent in every job's
result, so pydantic only, like the API's messages."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, field_validator


class PaintSeparation(BaseModel):
    """What the initial view says about the paint: ``ok`` False means the cell cannot tell it from the
    metal (``reason``) and refuses the piece; ``warnings`` name a borderline risk."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)
    ok: bool = Field(description="false: the job ended paint_not_separable, nothing was cut")
    reason: str = Field("", max_length=500, description="why not, in words")
    delta_e: float | None = Field(None, ge=0, description="CIE76 between the paint and the nearest metal colour "
                                  "the initial view showed")
    paint_share: float = Field(0.0, ge=0, le=1, description="of the piece's points in the initial view taken as paint")
    band_width_m: float | None = Field(None, ge=0, description="width of what was taken as paint (a line: its "
                                       "spray width)")
    paint_lab: list[float] | None = Field(None, max_length=3, description="L* a* b* of the paint on this piece")
    metal_lab: list[list[float]] = Field(default_factory=list, max_length=8,
                                         description="L* a* b* of the metal's colours")
    warnings: list[str] = Field(default_factory=list, max_length=10)

    @field_validator("delta_e", "band_width_m", "paint_share", mode="before")
    @classmethod
    def _round(cls, v):
        return None if v is None else round(float(v), 4)
