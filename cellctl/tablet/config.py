"""configs/tablet.yaml: where the web app listens, how it reaches the cells, and who may log in."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from configs.loading import load_yaml_model

USER_PATTERN = r"^[A-Za-z0-9_.@-]{1,64}$"


class TabletConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    host: str = Field("127.0.0.1", min_length=1, description="address the web app listens on (0.0.0.0: the yard "
                                                              "network)")
    port: int = Field(8080, ge=1, le=65535)
    title: str = Field("scrapcell", max_length=64)
    zenoh_mode: Literal["client", "peer"] = "client"
    connect: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"], max_length=16,
                               description="a cell's endpoint or the yard router's")
    zenoh_config: Path | None = Field(None, description="a Zenoh JSON5 file with this app's router credentials "
                                                        "(deploy/zenoh/operator.json5 or viewer.json5)")
    tls_ca: Path | None = Field(None, description="the yard's CA certificate (deploy/make-certs.sh), for a tls/ "
                                                  "endpoint: the yard router listens on TLS only")
    https_cert: Path | None = Field(None, description="the app's certificate for HTTPS pages (deploy/make-certs.sh DIR "
                                                      "tablet NAME): page logins and sessions do not cross the yard "
                                                      "network in clear; the tablets trust the yard's ca.crt")
    https_key: Path | None = Field(None, description="its private key (mode 600)")
    accounts_file: Path = Field(Path("runs/tablet/accounts.yaml"), description="page logins, made with "
                                                                              "`cellctl tablet --add-user`")
    state_dir: Path = Field(Path("runs/tablet"), description="the session secret and the fetched job files")
    real_scene: str | None = Field(None, max_length=500, description="the scene file a real (not twin) cell's jobs "
                                                                    "name: its initial views and workspace")
    refresh_s: float = Field(1.0, ge=0.1, le=30, description="how often each cell's status is read")
    query_timeout_s: float = Field(3.0, ge=0.2, le=60)
    max_points: int = Field(20000, ge=100, le=500000, description="the 3-D view's scanned surface is thinned to "
                                                                  "this many points")

    @field_validator("connect")
    @classmethod
    def _endpoints(cls, v: list[str]) -> list[str]:
        for ep in v:
            if not ep.startswith(("tcp/", "tls/", "udp/", "quic/")):
                raise ValueError(f"{ep!r} is not a Zenoh endpoint like tcp/192.168.1.10:7447")
        return v

    @model_validator(mode="after")
    def _https_pair(self) -> "TabletConfig":
        if (self.https_cert is None) != (self.https_key is None):
            raise ValueError("https_cert and https_key go together (deploy/make-certs.sh DIR tablet NAME makes both)")
        return self

    @field_validator("zenoh_config", "tls_ca", "https_cert", "https_key")
    @classmethod
    def _exists(cls, v: Path | None) -> Path | None:
        if v is not None and not v.is_file():
            raise ValueError(f"{v} does not exist")
        return v


def load_config(path: str | Path) -> TabletConfig:
    return load_yaml_model(path, TabletConfig, what="tablet config")
