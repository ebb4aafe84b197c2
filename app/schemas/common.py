"""The shared pieces of the public contract's models: strict number types, the `Model`
base (extra fields forbidden, finite floats) and the error body."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field

from app.errors import CODES

#: Numbers are strict (issue 11.10): `true` or `"1"` is not a number (it moved a joint to 1 rad);
#: an integer is a number. Integers are strict likewise: `true`, `"1"` and `1.0` are refused.
Finite = Annotated[float, Field(allow_inf_nan=False, strict=True)]
Unit = Annotated[float, Field(ge=0.0, le=1.0, allow_inf_nan=False, strict=True)]
Int = Annotated[int, Field(strict=True)]
Bool = Annotated[bool, Field(strict=True)]
Duration = Annotated[float, Field(gt=0.0, le=600.0, allow_inf_nan=False, strict=True)]
Speed = Annotated[float, Field(gt=0.0, le=1.0, allow_inf_nan=False, strict=True)]
DxlIdValue = Annotated[int, Field(ge=0, le=252, strict=True)]


class Model(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


# ---------------------------------------------------------------- errors


class ErrorBody(Model):
    detail: str | list[dict[str, object]]
    code: str = Field(description="a stable machine code of the error table (`app.errors`): "
                      + "; ".join(f"`{c.code}` ({c.status}) {c.meaning}"
                                  for c in CODES.values() if c.status is not None),
                      json_schema_extra={"enum": [c for c, r in CODES.items()
                                                  if r.status is not None]})
