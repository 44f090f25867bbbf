"""TextIM's interaction extraction (SPEC-textim §3, §11 item 2): prompt, answer check and content
amendment, retries, cache, the openai backend against a local HTTP server, rules vs oracle on
synthetic captions, and the part mask."""
from __future__ import annotations

import json
import re
import sqlite3
import threading
from collections import Counter
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from party.data.synthetic import make_action, make_captions, sample_specs, single_spec
from party.data.synthetic.captions import caption_lines
from party.text.interactions.extract import (FallbackRateError, InteractionCache, InteractionsConfig,
                                          OracleInteractionBackend, RulesInteractionBackend,
                                          build_interaction_backend, extract_with_retries, fill_interactions,
                                          oracle_answer, part_mask, result_from_answer, rules_answer)
from party.text.interactions.prompt import (ASPECTS, FEW_SHOT, PARTS, SYSTEM, InteractionFormatError,
                                                     build_messages, map_part, parse_answer, prompt_fingerprint)
from party.motion.parts import group_index

ROOT = Path(__file__).resolve().parents[2]
SYN = OmegaConf.load(ROOT / "conf/dataset/synthetic.yaml")
KICK = "someone walks forward and kicks a ball with the right foot."
CLEAN = "a person cleans the table with the right hand while looking at the watch on the left wrist."
CFG = InteractionsConfig(backend="rules")


def res(answer: str, caption: str, **kw):
    return result_from_answer(answer, caption, InteractionsConfig(**kw) if kw else CFG)


# ------------------------------------------------------------------ prompt
def test_prompt_has_aspects_examples_and_question():
    msgs = build_messages("a man throws a ball with his left hand.")
    assert msgs[0]["role"] == "system"
    for text in (*ASPECTS, "If the sentence does not say which side, list both sides.",
                 "Copy the phrase word for word from the sentence."):
        assert text in msgs[0]["content"]
    assert len(msgs) == 1 + 2 * len(FEW_SHOT) + 1 and len(FEW_SHOT) == 6
    assert [m["role"] for m in msgs[1:-1]] == ["user", "assistant"] * 6
    assert msgs[4]["content"] == "left arm, right arm: picks up a box with both hands and puts it on a shelf"
    assert msgs[-1] == {"role": "user", "content": "Provide your answer for the following sentence: "
                                                   "\"a man throws a ball with his left hand.\""}


def test_fingerprint_follows_the_prompt():
    fp = prompt_fingerprint()
    assert fp == prompt_fingerprint() and re.fullmatch(r"[0-9a-f]{12}", fp)
    assert prompt_fingerprint(system=SYSTEM + " Be brief.") != fp
    assert prompt_fingerprint(examples=FEW_SHOT[:-1]) != fp
    assert prompt_fingerprint(feedback="Try again: {error}") != fp


def test_few_shot_answers_pass_their_own_check():
    for caption, answer in FEW_SHOT:
        r = res(answer, caption)
        assert r.c_inter == ("; ".join(ln.split(": ", 1)[1] for ln in answer.splitlines())
                             if answer != "none" else None)


# ------------------------------------------------------------------ answers
def test_single_and_multi_part_lines():
    r = res("left arm: wipes the table with their left hand", FEW_SHOT[0][0])
    assert r.parts == ("left_arm",) and r.c_inter == "wipes the table with their left hand"
    r = res(FEW_SHOT[1][1], FEW_SHOT[1][0])
    assert r.parts == ("left_arm", "right_arm")
    assert r.c_inter == "picks up a box with both hands and puts it on a shelf" and r.c_non is None


def test_several_interactions_merge_in_caption_order():
    answer = "left arm: looking at the watch on the left wrist\nright arm: cleans the table with the right hand"
    r = res(answer, CLEAN)
    assert r.parts == ("left_arm", "right_arm")
    assert r.c_inter == "cleans the table with the right hand; looking at the watch on the left wrist"
    assert r.phrases == ("cleans the table with the right hand", "looking at the watch on the left wrist")
    r = res("right leg: kicks a ball\nright arm, torso: walks forward", KICK)
    assert r.parts == ("torso", "right_arm", "right_leg") and r.c_inter == "walks forward; kicks a ball"


@pytest.mark.parametrize("answer", ["none", "None.", "  'none'  ", "<think>hmm</think>\nnone"])
def test_none(answer):
    r = res(answer, KICK)
    assert r.parts == () and r.c_inter is None and r.c_non == KICK and not r.fallback


def test_none_with_other_lines_is_rejected():
    with pytest.raises(InteractionFormatError, match="whole answer"):
        parse_answer("none\nright leg: kicks a ball", KICK)


@pytest.mark.parametrize("name,unsided,parts", [
    ("left wrist", "both", ("left_arm",)), ("right knee", "both", ("right_leg",)), ("hips", "both", ("pelvis",)),
    ("hand", "both", ("left_arm", "right_arm")), ("hand", "right", ("right_arm",)),
    ("Both Hands", "right", ("left_arm", "right_arm")), ("left hip", "both", ("left_leg",)),
    ("collarbone", "right", ("right_arm",)), ("Right_Leg", "both", ("right_leg",)), ("chest", "both", ("torso",)),
    ("feet", "right", ("left_leg", "right_leg")), ("lap", "both", ("pelvis",)), ("nose", "both", ()),
])
def test_part_mapping(name, unsided, parts):
    assert map_part(name, unsided) == parts


def test_mapping_in_answer_lines():
    cap = "a person touches the left wrist, bends the right knee and sways the hips while waving a hand."
    r = res("left wrist: touches the left wrist\nRIGHT KNEE: bends the right knee\nhips: sways the hips\n"
            "hand: waving a hand", cap)
    assert r.parts == ("pelvis", "left_arm", "right_arm", "right_leg")
    r = res("hand: waving a hand", cap, unsided="right")
    assert r.parts == ("right_arm",)


@pytest.mark.parametrize("answer,match", [
    ("nose: kicks a ball with the right foot", "names no body part"),
    ("kicks a ball with the right foot", "is not '<body part>"),
    ("right leg:", "is not '<body part>"),
    ("", "empty"),
])
def test_format_failures(answer, match):
    with pytest.raises(InteractionFormatError, match=match):
        parse_answer(answer, KICK)


def test_phrase_normalised_amended_or_rejected():
    r = res("Right Leg: Kicks a ball,  with the RIGHT foot!", KICK)          # case / space / punctuation
    assert r.c_inter == "kicks a ball with the right foot" and r.amended == 0
    r = res("right leg: kick the ball with right foot", KICK)               # not a substring: amended
    assert r.c_inter == "kicks a ball with the right foot" and r.amended == 1
    assert r.c_non == "someone walks forward"
    with pytest.raises(InteractionFormatError, match="not in the sentence"):
        parse_answer("right leg: dances a slow tango on the stage", KICK)
    with pytest.raises(InteractionFormatError, match="not in the sentence"):  # the 60% share is a setting
        parse_answer("right leg: kick the ball with right foot", KICK, span_overlap=0.95)


def test_c_non():
    r = res("right leg: kicks a ball with the right foot", KICK)
    assert r.c_non == "someone walks forward"
    cap = "a man waves with the right hand, then walks forward and sits down."
    assert res("right arm: waves with the right hand", cap).c_non == "a man walks forward and sits down"
    assert res("right arm: waves with the right hand", "a man waves with the right hand.").c_non is None
    cap = "a person walks forward while holding a cup in the left hand and then sits down."
    assert res("left arm: holding a cup in the left hand", cap).c_non == "a person walks forward, sits down"


# ------------------------------------------------------------------ retries
class ScriptedChat:
    def __init__(self, answers):
        self.answers, self.calls = list(answers), []

    def __call__(self, messages, temperature):
        self.calls.append((json.loads(json.dumps(messages)), temperature))
        return self.answers[min(len(self.calls), len(self.answers)) - 1]


def test_retry_with_feedback_then_none():
    chat = ScriptedChat(["The person kicks.", "right leg: moonwalks backwards", "kick: kicks"])
    r = extract_with_retries(KICK, chat, InteractionsConfig(backend="openai"))
    assert len(chat.calls) == 3
    assert r.fallback and r.parts == () and r.c_inter is None and r.c_non == KICK.strip()
    assert r.attempts == 3 and r.format_failures == 3 and r.reason.startswith("format: ") and r.cacheable
    first, second, third = (m for m, _ in chat.calls)
    assert chat.calls[0][1] == 0.0
    assert len(second) == len(first) + 2 and second[:len(first)] == first
    assert second[-2] == {"role": "assistant", "content": "The person kicks."}
    assert "not accepted" in second[-1]["content"] and "is not '<body part>" in second[-1]["content"]
    assert "not in the sentence" in third[-1]["content"] and len(third) == len(first) + 4


def test_retry_succeeds_on_second_attempt():
    chat = ScriptedChat(["Sure! right leg kicks", "right leg: kicks a ball with the right foot"])
    r = extract_with_retries(KICK, chat, InteractionsConfig(backend="openai"))
    assert len(chat.calls) == 2 and not r.fallback and r.attempts == 2 and r.parts == ("right_leg",)
    chat = ScriptedChat(["bad"] * 5)
    r = extract_with_retries(KICK, chat, InteractionsConfig(backend="openai", max_attempts=1))
    assert len(chat.calls) == 1 and r.fallback


# ------------------------------------------------------------------ cache and fill
class CountingBackend:
    name, model, fingerprint = "fake", "fake-model", "f" * 12

    def __init__(self, answers: dict, cfg: InteractionsConfig):
        self.answers, self.cfg, self.requests = answers, cfg, Counter()
        self.lock = threading.Lock()

    def extract(self, caption):
        with self.lock:
            self.requests[caption] += 1
        return extract_with_retries(caption, lambda m, t: self.answers[caption], self.cfg)


def test_rerun_is_served_from_the_cache(tmp_path):
    cfg = InteractionsConfig(backend="openai", concurrency=3, cache_path=str(tmp_path / "c.sqlite"))
    answers = {KICK: "right leg: kicks a ball with the right foot", CLEAN: "\n".join(FEW_SHOT[3][1:]),
               "a person jogs.": "none", "a man claps.": "left arm, right arm: claps"}
    backend = CountingBackend(answers, cfg)
    with InteractionCache(cfg.cache_path) as cache:
        first, stats = fill_interactions(list(answers) + [KICK], backend, cache, cfg, progress=False)
        assert stats["misses"] == 4 and sum(backend.requests.values()) == 4 and cache.count() == 4
    with InteractionCache(cfg.cache_path) as cache:
        again, stats = fill_interactions(list(answers), backend, cache, cfg, progress=False)
    assert stats["hits"] == 4 and stats["misses"] == 0 and stats["calls"] == 0
    assert sum(backend.requests.values()) == 4
    assert {c: r.to_json() for c, r in again.items()} == {c: r.to_json() for c, r in first.items()}
    assert again[KICK].c_non == "someone walks forward" and again["a man claps."].parts == ("left_arm", "right_arm")
    # other validator settings are other answers
    with InteractionCache(cfg.cache_path) as cache:
        _, stats = fill_interactions([KICK], backend, cache, InteractionsConfig(backend="openai", unsided="right"),
                                     progress=False)
    assert stats["misses"] == 1


def test_changed_prompt_under_the_same_version_is_refused(tmp_path):
    cfg = InteractionsConfig(cache_path=str(tmp_path / "c.sqlite"))
    backend = CountingBackend({KICK: "none"}, cfg)
    with InteractionCache(cfg.cache_path) as cache:
        fill_interactions([KICK], backend, cache, cfg, progress=False)
        backend.fingerprint = "0" * 12
        with pytest.raises(ValueError, match="prompt_version"):
            fill_interactions([KICK], backend, cache, cfg, progress=False)


def test_fallback_rate_limit(tmp_path):
    caps = [f"a person waves {i} times." for i in range(5)]
    answers = {c: ("none" if i < 4 else "gibberish") for i, c in enumerate(caps)}        # 1 of 5 falls back
    cfg = InteractionsConfig(cache_path=str(tmp_path / "c.sqlite"), max_fallback_rate=0.2)
    with InteractionCache(cfg.cache_path) as cache:
        _, stats = fill_interactions(caps, CountingBackend(answers, cfg), cache, cfg, progress=False)
        assert stats["fallbacks"] == 1
        strict = InteractionsConfig(cache_path=cfg.cache_path, max_fallback_rate=0.1)
        with pytest.raises(FallbackRateError, match=r"1 of 5 captions \(20\.0%\).*max_fallback_rate=0\.1"):
            fill_interactions(caps, CountingBackend(answers, cfg), cache, strict, progress=False)


# ------------------------------------------------------------------ openai backend, local server
class StubServer:
    """An OpenAI-compatible chat server on 127.0.0.1 answering from a script per caption."""

    def __init__(self, script: dict, default: str = "none"):
        self.script, self.default = script, default
        self.requests, self.bodies, self.auth = Counter(), [], []
        stub = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *a):
                pass

            def do_POST(self):
                body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
                q = [m["content"] for m in body["messages"] if m["content"].startswith("Provide your answer")]
                caption = re.search(r'sentence: "(.*)"$', q[-1]).group(1)
                n = stub.requests[caption]
                stub.requests[caption] += 1
                stub.bodies.append(body)
                stub.auth.append(self.headers.get("Authorization"))
                steps = stub.script.get(caption, [])
                content = steps[n] if n < len(steps) else stub.default
                data = json.dumps({"id": "x", "object": "chat.completion", "model": body["model"], "choices": [
                    {"index": 0, "finish_reason": "stop", "message": {"role": "assistant", "content": content}}]})
                self.send_response(200)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data.encode())

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.server.daemon_threads = True
        self.thread = threading.Thread(target=self.server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)

    @property
    def base_url(self):
        return f"http://127.0.0.1:{self.server.server_address[1]}/v1"

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.server.shutdown()
        self.server.server_close()


def test_openai_backend_against_a_local_server(tmp_path, monkeypatch):
    monkeypatch.setenv("TEXTIM_TEST_KEY", "sk-textim-test-key-42")
    bad = "a person jogs in a circle counterclockwise while juggling."
    script = {KICK: ["right leg: kicks a ball with the right foot"],
              CLEAN: ["The person cleans.", FEW_SHOT[3][1]],
              bad: ["I am not sure.", "juggling: juggling", "left arm: dances a tango"]}
    with StubServer(script) as srv:
        cfg = InteractionsConfig(backend="openai", model="stub-model", base_url=srv.base_url,
                                 api_key_env="TEXTIM_TEST_KEY", concurrency=2, timeout_s=5, max_retries=0,
                                 cache_path=str(tmp_path / "c.sqlite"), max_fallback_rate=0.5)
        backend = build_interaction_backend(cfg)
        with InteractionCache(cfg.cache_path) as cache:
            out, stats = fill_interactions([KICK, CLEAN, bad], backend, cache, cfg, progress=False)
            assert srv.requests == Counter({KICK: 1, CLEAN: 2, bad: 3})
            assert stats["calls"] == 6 and stats["fallbacks"] == 1 and stats["format_failures"] == 4
            _, stats = fill_interactions([KICK, CLEAN, bad], backend, cache, cfg, progress=False)
        assert stats["calls"] == 0 and stats["hits"] == 3 and sum(srv.requests.values()) == 6
    assert out[KICK].parts == ("right_leg",) and out[KICK].c_non == "someone walks forward"
    assert out[CLEAN].parts == ("left_arm", "right_arm") and out[CLEAN].attempts == 2
    assert out[bad].fallback and out[bad].parts == () and out[bad].attempts == 3
    first = [b for b in srv.bodies if b["messages"][-1]["content"].endswith(f'"{KICK}"')][0]
    assert first["model"] == "stub-model" and first["temperature"] == 0.0
    assert first["messages"] == build_messages(KICK)
    assert set(srv.auth) == {"Bearer sk-textim-test-key-42"}
    assert b"sk-textim-test-key-42" not in Path(cfg.cache_path).read_bytes()
    db = sqlite3.connect(cfg.cache_path)
    q = "SELECT COUNT(*) FROM interactions WHERE backend='openai' AND model='stub-model'"
    assert db.execute(q).fetchone()[0] == 3
    db.close()


# ------------------------------------------------------------------ rules and oracle
def test_rules_on_the_few_shot_examples():
    backend = RulesInteractionBackend(CFG)
    for caption, answer in FEW_SHOT:
        assert backend.extract(caption).parts == res(answer, caption).parts, caption
    assert rules_answer(KICK) == "right leg: kicks a ball with the right foot"
    assert rules_answer("a person walks forward, swinging their arms.") == "none"
    assert rules_answer("the man turns around over his left shoulder.") == "none"
    r = backend.extract("a person scratches the head with the left hand and then hops on the right foot.")
    assert r.parts == ("left_arm", "right_leg")
    assert r.phrases == ("scratches the head with the left hand", "hops on the right foot")
    assert RulesInteractionBackend(InteractionsConfig(unsided="right")).extract("a man throws a ball.").parts \
        == ("right_arm",)


def _synthetic_entries(n, seed):
    specs = sample_specs(SYN, np.random.default_rng(seed), n=n)
    out = []
    for sp in specs:
        for c in make_captions(sp, np.random.default_rng([seed, sp.index]), SYN.synthetic.captions, float(SYN.fps)):
            out.append((c["caption"], sp, None if c["start"] == c["end"] == 0.0 else int(c["start"] > 0)))
    return out


def test_rules_and_oracle_agree_on_synthetic_captions():
    entries = _synthetic_entries(40, 5)
    oracle, rules = OracleInteractionBackend(CFG, entries), RulesInteractionBackend(CFG)
    caps = list(dict.fromkeys(c for c, _, _ in entries))
    limbs = {"left_arm", "right_arm", "left_leg", "right_leg"}
    same = limbs_same = marked = 0
    for c in caps:
        o, r = oracle.extract(c), rules.extract(c)
        assert set(o.parts) <= limbs, c                                # the oracle marks sided limbs only
        for limb in ("arm", "leg"):                                    # never the other side
            os_, rs = ({s for s in ("left", "right") if f"{s}_{limb}" in x.parts} for x in (o, r))
            assert not (len(os_) == len(rs) == 1 and os_ != rs), (c, o.parts, r.parts)
        same += o.parts == r.parts
        limbs_same += set(o.parts) == set(r.parts) & limbs
        marked += bool(o.parts)
    # "walks forward, swinging the arms" reads as the gait's swing, which the synthetic set also
    # writes for an arms 'swing' action: the few disagreements
    assert len(caps) > 100 and marked / len(caps) > 0.5
    assert limbs_same / len(caps) >= 0.97 and same / len(caps) >= 0.95, (limbs_same, same, len(caps))


def test_oracle_phrases_and_strictness():
    sp = single_spec(make_action("kick", SYN.synthetic.legs, None, side="left"),
                     make_action("wave", SYN.synthetic.arms, None, side="right"), float(SYN.fps))
    cap = "a person kicks with the left leg while waving the right hand."
    ans = oracle_answer(cap, sp)
    assert ans == "left leg: kicks with the left leg\nright arm: waving the right hand"
    r = res(ans, cap)
    assert r.parts == ("right_arm", "left_leg") and r.c_non is None
    with pytest.raises(ValueError, match="does not mention the legs action 'kick'"):
        oracle_answer("a person waves the right hand.", sp)


def test_oracle_backend_reads_a_synthetic_dataset(tmp_path):
    specs = [single_spec(make_action("stand", SYN.synthetic.legs, None),
                         make_action(a, SYN.synthetic.arms, None, side=s), float(SYN.fps), name=f"{i:06d}")
             for i, (a, s) in enumerate([("wave", "left"), ("point", "right"), ("clap", None)])]
    (tmp_path / "texts").mkdir()
    lines, caps = [], {}
    for sp in specs:
        c = make_captions(sp, np.random.default_rng(1), SYN.synthetic.captions, float(SYN.fps))
        caps[sp.name] = [x["caption"] for x in c]
        (tmp_path / "texts" / f"{sp.name}.txt").write_text(caption_lines(c))
        lines.append(json.dumps({"name": sp.name, "split": "train", **sp.to_dict()}))
    (tmp_path / "specs.jsonl").write_text("\n".join(lines) + "\n")
    backend = build_interaction_backend({"backend": "oracle", "oracle_root": str(tmp_path)})
    want = {"000000": ("left_arm",), "000001": ("right_arm",), "000002": ("left_arm", "right_arm")}
    for name, parts in want.items():
        for c in caps[name]:
            assert backend.extract(c).parts == parts, c
    with pytest.raises(KeyError, match="not a caption of the synthetic dataset"):
        backend.extract("a person moonwalks.")


# ------------------------------------------------------------------ config and mask
def test_config_checks():
    assert InteractionsConfig().temperature == 0 and InteractionsConfig().max_attempts == 3
    assert InteractionsConfig().span_overlap == 0.6 and InteractionsConfig().max_fallback_rate == 0.2
    with pytest.raises(ValueError, match="unknown keys.*api_key"):
        InteractionsConfig.from_cfg({"backend": "rules", "api_key": "sk-x"})
    with pytest.raises(ValueError, match="unsided"):
        InteractionsConfig(unsided="left")
    with pytest.raises(ValueError, match="oracle_root"):
        build_interaction_backend({"backend": "oracle"})


def _hml3d_channels(j: int) -> list[int]:
    """HumanML3D layout: root 4 | ric 21x3 | rot6d 21x6 | local velocity 22x3 | contacts 4."""
    return ([4 + 3 * (j - 1) + k for k in range(3)] + [67 + 6 * (j - 1) + k for k in range(6)]
            + [193 + 3 * j + k for k in range(3)])


def test_part_mask():
    groups = OmegaConf.load(ROOT / "conf/dataset/parts/t2m.yaml").groups.textim6
    idx = group_index(22, groups)
    assert tuple(idx) == PARTS
    m = part_mask(["left_arm"], idx)
    assert m.dtype == bool and m.shape == (263,) and m.sum() == 48
    assert np.flatnonzero(m).tolist() == sorted(c for j in (13, 16, 18, 20) for c in _hml3d_channels(j))
    assert [int(part_mask([p], idx).sum()) for p in PARTS] == [7, 60, 48, 48, 50, 50]
    assert part_mask(PARTS, idx).all() and not part_mask([], idx).any()
    both = part_mask(["left_arm", "right_leg"], idx)
    assert both.sum() == 98 and not (both & ~(m | part_mask(["right_leg"], idx))).any()
    with pytest.raises(ValueError, match="'left_hand' is not a group"):
        part_mask(["left_hand"], idx)
