"""The README's node/topic diagram, generated from the contract (Mermaid):
`python -m msg_schemas.diagram` prints it; a test keeps the README in step."""

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


if __name__ == "__main__":
    print(mermaid())
