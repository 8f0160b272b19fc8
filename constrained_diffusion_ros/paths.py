"""Where the package's shipped files are, in a source checkout, a venv or a colcon install."""

from __future__ import annotations

from pathlib import Path

PACKAGE = "constrained_diffusion_ros"
SOURCE_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_MODEL = "pusht_lowdim"


def share_dir() -> Path:
    """The checkout when running from source (editable install), else the ament share dir."""
    if (SOURCE_ROOT / "package.xml").is_file():
        return SOURCE_ROOT
    from ament_index_python.packages import get_package_share_directory

    return Path(get_package_share_directory(PACKAGE))


def default_model_dir() -> Path:
    return share_dir() / "models" / DEFAULT_MODEL


def config_dir() -> Path:
    return share_dir() / "config"
