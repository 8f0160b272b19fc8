"""The README's node/topic diagram (Mermaid) and interface table, generated from the
contract: `python -m msg_schemas.diagram` prints both; a test keeps the README in step."""

from __future__ import annotations

from msg_schemas.contract import SERVICES, TOPICS


def mermaid() -> str:
    lines = ["```mermaid", "flowchart LR",
             "  recorder[(\"recorder<br/>every topic -> rosbag2 MCAP\")]"]
    for topic in TOPICS.values():
        short = topic.type.split("/")[-1]
        others = [s for s in topic.subscribers if s != "recorder"] or ["recorder"]
        for subscriber in others:
            lines.append(f"  {topic.publisher} -- \"{topic.name}<br/>{short}\" --> "
                         f"{subscriber}")
    for index, service in enumerate(SERVICES.values()):
        short = service.type.split("/")[-1]
        lines.append(f"  service{index}{{{{\"{service.name}<br/>{short}\"}}}} -.- "
                     f"{service.publisher}")
    lines.append("```")
    return "\n".join(lines)


QOS_TEXT = {
    "sensor": "reliable; publisher keeps 1000 (transient local), subscribers volatile",
    "latched": "reliable, transient local, 10,000 deep (late joiners get what is in force)",
    "map": "reliable, transient local, the latest only (as nav2's map server)",
    "clock": "reliable, volatile, no history",
    "services": "services default",
}


def interface_table() -> str:
    """Every topic and service: name (relative ones resolve in the node's namespace, `pusht`
    by default), type, QoS, units and frame, who publishes and who listens."""
    lines = ["| name | type | QoS | units, frame | from -> to | what |",
             "| --- | --- | --- | --- | --- | --- |"]
    for endpoint in [*TOPICS.values(), *SERVICES.values()]:
        to = ", ".join(endpoint.subscribers) or "callers"
        lines.append(f"| `{endpoint.name}` | `{endpoint.type}` | {QOS_TEXT[endpoint.qos]} | "
                     f"{endpoint.units or '-'} | {endpoint.publisher} -> {to} | "
                     f"{endpoint.description} |")
    return "\n".join(lines)


if __name__ == "__main__":
    print(mermaid())
    print()
    print(interface_table())
