"""The user docs say what the code does: the README is a guide, the protocol's hello example is what the server
sends, and every document names the same protocol revision (issue 35)."""

import json
import re
from pathlib import Path

from streamer import protocol as P

ROOT = Path(__file__).resolve().parent.parent
# Measurement histories live in benchmarks/README.md and benchmarks/results/; docs/performance.md is generated
# from the results and names the machine once.
USER_DOCS = sorted([ROOT / "README.md", ROOT / "MODEL_CARD.md", *ROOT.glob("clients/**/README.md"),
                    *(p for p in (ROOT / "docs").glob("*.md") if p.name != "performance.md")])
HASH = re.compile(r"(?<![\w./-])(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}(?![\w-])")


def test_the_readme_is_a_guide_of_at_most_2000_words():
    assert len((ROOT / "README.md").read_text().split()) <= 2000


def test_the_hash_pattern_finds_commit_hashes_and_nothing_else():
    assert HASH.findall("measured on main at f85e817, code (3724c4a0) and 1f45115.") == ["f85e817", "3724c4a0", "1f45115"]
    assert not HASH.findall("1e-4, 0xff, DGA1, deadbeef, 1234567, speech_2_x_1_0, frame_a1b2c3d4, /ab12cd3ef/")


def test_user_docs_hold_no_commit_hashes_or_load_averages():
    found = []
    for p in USER_DOCS:
        for n, line in enumerate(p.read_text().splitlines(), 1):
            if HASH.search(line) or re.search(r"load average|(?<!real-time )\bload ~?\d", line, re.I):
                found.append(f"{p.relative_to(ROOT)}:{n}: {line.strip()[:100]}")
    assert not found, "move these to benchmarks/README.md:\n" + "\n".join(found)


def test_the_protocol_docs_hello_example_is_what_the_server_sends_for_the_default_model():
    from dimgestor.streaming.checkpoint import load_checkpoint
    from streamer.pose import HumanoidRig, load_humanoid_map

    text = (ROOT / "docs" / "protocol.md").read_text()
    doc = json.loads(re.search(r"```json\n(\{\"type\": \"hello\".*?)\n```", text, re.S).group(1))
    bundle = load_checkpoint(None)
    sk = bundle.skeleton
    rig = HumanoidRig.build(sk.names, sk.parents, sk.offsets, load_humanoid_map(None))
    sent = json.loads(json.dumps(P.hello(P.SkeletonInfo.from_skeleton(sk), rig.mapping(sk.names),
                                         int(bundle.feature_spec.fps), bundle.model.lookahead_s, True,
                                         window_ms=200, source="ws")))
    assert doc["lookahead_s"] == sent["lookahead_s"] == 0.35
    for key in ("type", "protocol", "revision", "server", "fps", "encoding", "audio", "max_message_bytes",
                "binary_frame_bytes", "window_ms", "source"):
        assert doc[key] == sent[key], key
    for key in ("joints", "parents", "offsets", "rest_rotations"):
        shown = [v for v in doc["skeleton"][key] if v != "..."]  # the example elides the rest with "..."
        assert shown == sent["skeleton"][key][:len(shown)], key
    assert {k: v for k, v in doc["humanoid"].items() if k != "..."}.items() <= sent["humanoid"].items()


def test_every_doc_that_names_the_servers_revision_names_the_current_one():
    named = {}
    for p in [ROOT / "README.md", ROOT / "docs" / "protocol.md", ROOT / "clients" / "README.md",
              *ROOT.glob("clients/*/README.md")]:
        for m in re.finditer(r"server's current revision is (\d+)", p.read_text()):
            named.setdefault(int(m.group(1)), []).append(p.relative_to(ROOT))
    assert named and set(named) == {P.REVISION}, named
    revisions = (ROOT / "docs" / "protocol.md").read_text().split("## Revisions", 1)[1].split("\n## ", 1)[0]
    table = re.findall(r"^\| (\d+) \| ", revisions, re.M)
    assert max(map(int, table)) == P.REVISION  # the Revisions table ends at the current one
