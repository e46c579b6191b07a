"""The base of every ``config.toml`` section: unknown keys rejected, values validated on assignment.

Apart from :mod:`mazebot.config` so that the sections kept in modules of their own
(:mod:`mazebot.sim_config`) share it without importing the whole configuration.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field


class Section(BaseModel):
    """A config section: unknown keys rejected, values validated on assignment.

    ``defer_build``: a model's validator is built on its first use, not at import
    (https://docs.pydantic.dev/latest/api/config/#pydantic.config.ConfigDict.defer_build),
    so a command that needs one section (``mazebot motors stop``) does not pay for all.
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True, defer_build=True)


#: A Raspberry Pi GPIO by its BCM number (the 40-pin header's GPIO 0–27), for the motor and encoder pins.
BcmPin = Annotated[int, Field(ge=0, le=27)]
