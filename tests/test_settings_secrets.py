"""Issue 22.12: no message that prints a setting shows a secret: the start-up error for invalid
settings, a validator's message, pydantic's own error text and the settings' repr mask a URL's
password and every setting whose name says token, secret or password."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from app.cli import main
from app.config import Settings, settings_error
from app.config.settings import is_secret, mask_url

PASSWORD = "pw-Zq81-s3cret"


@pytest.mark.parametrize("url", [
    f"mqtts://bob:{PASSWORD}@:8883",            # names no host
    f"mqtx://bob:{PASSWORD}@broker.lab",        # not an MQTT URL
    f"mqtt://bob:{PASSWORD}@broker.lab:99999",  # bad port
    f"mqtt://bob:p@{PASSWORD}@:1",              # an @ in the password
])
def test_the_start_up_error_masks_the_mqtt_password(
        url: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setenv("ARMSERVER_MQTT_URL", url)
    assert main(["serve", "--port", "0"]) == 2
    err = capsys.readouterr().err
    assert "ARMSERVER_MQTT_URL=" in err and "bob:***@" in err, err
    assert PASSWORD not in err and "s3cret" not in err, err


def test_pydantic_error_text_and_repr_carry_no_secret() -> None:
    with pytest.raises(ValidationError) as caught:
        Settings(mqtt_url=f"mqtt://bob:{PASSWORD}@:1")
    assert PASSWORD not in str(caught.value) and "s3cret" not in repr(caught.value)
    s = Settings(mqtt_url=f"mqtt://bob:{PASSWORD}@broker.lab", operator_tokens="alice:tok-Qx9",
                 instructor_tokens="tok-Zz7", viewer_tokens="")
    for text in (repr(s), str(s)):
        assert PASSWORD not in text and "tok-Qx9" not in text and "tok-Zz7" not in text, text
        assert "mqtt://bob:***@broker.lab" in text and "operator_tokens='***'" in text
        assert "viewer_tokens=''" in text  # nothing to hide: shown as it is
    assert s.mqtt_url == f"mqtt://bob:{PASSWORD}@broker.lab"  # the value itself is whole


def test_a_secret_setting_is_masked_in_the_start_up_error() -> None:
    with pytest.raises(ValidationError) as caught:
        Settings(operator_tokens=["alice:tok-Qx9"])  # not a string
    text = settings_error(caught.value)
    assert "tok-Qx9" not in text, text
    assert "ARMSERVER_OPERATOR_TOKENS='***': Input should be a valid string" in text


def test_which_names_are_secret() -> None:
    assert all(map(is_secret, ["operator_tokens", "viewer_tokens", "instructor_tokens",
                               "mqtt_password", "api_secret"]))
    assert not any(map(is_secret, ["tokens_file", "mqtt_url", "host", "data_dir"]))
    assert mask_url("mqtt://u:pw@h mqtts://v:x@y:1/p") == "mqtt://u:***@h mqtts://v:***@y:1/p"
    assert mask_url("mqtt://user@host and plain text") == "mqtt://user@host and plain text"
