"""Config errors name the user's key, not pydantic's names of the alternatives it tried."""

import pytest

from bsipipe.commands.track import TrackConfig
from bsipipe.config import validate
from bsipipe.errors import InputError


def test_a_union_key_is_named_as_the_user_wrote_it():
    """'diameter_px: 4px' had been reported under the key 'diameter_px.constrained-float'."""
    with pytest.raises(InputError) as e:
        validate(TrackConfig, {"views": {"cam1": "frames/"}, "diameter_px": "4px"}, "track.yaml")
    assert e.value.key == "diameter_px" and "constrained" not in str(e.value), str(e.value)
    assert "more problem" in str(e.value) and "with this key" in str(e.value)
