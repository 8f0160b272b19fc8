"""The topic contract is the one home of topic names: the README's diagram is generated from it,
every type exists, and no node writes a topic string of its own."""

from __future__ import annotations

import re
from pathlib import Path

from msg_schemas import SERVICES, TOPICS
from msg_schemas.diagram import interface_table, mermaid

REPO = Path(__file__).resolve().parents[2]


def test_readme_diagram_and_interface_table_are_the_generated_ones() -> None:
    readme = (REPO / "README.md").read_text()
    assert mermaid() in readme and interface_table() in readme


def test_every_interface_type_resolves_to_a_ros_class() -> None:
    for endpoint in [*TOPICS.values(), *SERVICES.values()]:
        package, kind, name = endpoint.type.split("/")
        cls = endpoint.message_class()
        assert cls.__module__.startswith(f"{package}.{kind}.") and cls.__name__ == name


def test_no_source_file_writes_a_topic_name_outside_the_contract() -> None:
    """Code names a topic by its contract key (`TOPICS["zones"]`), never by a spelling of its
    own: not "/pusht/zones" or "pusht/zones" anywhere, and no literal name at all where a
    publisher, subscription, client or service is made."""
    names = [e.name.lstrip("/") for e in [*TOPICS.values(), *SERVICES.values()]]
    # As a string literal; docstrings may mention a topic in backquotes.
    spelled = "|".join(f"[\"'][^\"'\\s]*/{re.escape(name)}[\"']" for name in names)
    made = r"create_(?:publisher|subscription|client|service)\([^,()]+,\s*f?[\"']"
    pattern = re.compile(f"{spelled}|{made}")
    sources = [*REPO.glob("constrained_diffusion_ros/**/*.py"), *REPO.glob("sim_bridge/*.py"),
               *REPO.glob("msg_schemas/*.py"), *REPO.glob("node_support/*.py"),
               *REPO.glob("scripts/*.py")]
    offenders = [str(path.relative_to(REPO)) for path in sources
                 if path.name != "contract.py" and pattern.search(path.read_text())]
    assert len(sources) > 20 and offenders == []


def test_names_are_relative_and_resolve_in_the_default_or_a_given_namespace() -> None:
    assert TOPICS["setpoint"].name == "setpoint"
    assert TOPICS["setpoint"].resolved() == "/pusht/setpoint"
    assert TOPICS["zones"].resolved("/robot1") == "/robot1/zones"
    assert TOPICS["zones"].resolved("/") == "/zones"
    assert SERVICES["reset"].type == "std_srvs/srv/Trigger"
