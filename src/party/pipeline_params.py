"""Which config keys a pipeline stage's outputs depend on: what dvc.yaml's ``params:`` lists.

DVC reruns a stage when one of the params it lists changes, and only then; a stage has to list
every key that changes its outputs, and no key that does not (else editing it reruns the stage
for nothing). ``tests/test_dvc_params.py`` checks dvc.yaml against this module.

``generator.generate`` serves two uses of ``party generate`` (``party.stages.generate``): the
pipeline's ``generate@<method>`` stage, which samples every clip of ``split`` into
``<generator.generated_dir>/<method>/``, and text-to-motion for people (``texts`` /
``texts_file`` in, files under ``out``). The keys of the second use alone are
``PEOPLE_ONLY_GENERATE_KEYS``; every other key of the block changes what the stage writes.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Iterable

from party.schema import GenGenerate

#: ``generator.generate`` keys read only when generating for people's texts: the texts, their
#: frame counts, the model folder or URI, the output folder and the file formats (marked
#: ``_people_only`` where the schema declares them, ``party.schema.GenGenerate``).
PEOPLE_ONLY_GENERATE_KEYS = frozenset(f.name for f in dataclasses.fields(GenGenerate) if f.metadata.get("people"))


def generate_params(fields: Iterable[str]) -> list[str]:
    """The ``generator.generate.<key>`` params of the ``generate`` stage, in the order of
    ``fields`` (the keys of the ``generator.generate`` block): every key but the people-only ones."""
    return [f"generator.generate.{k}" for k in fields if k not in PEOPLE_ONLY_GENERATE_KEYS]


#: The ``vqvae`` keys a tokenizer stage (``train_vqvae``, ``train_part_vqvae``, ``train_extra_vqvae``:
#: ``party.tokenizers.train``) reads, beside ``vqvae.tokenizers.<its stream>`` (``TOKENIZER_STREAM_KEY``)
#: and the stream itself (the stage's command): not the other streams' entries, the stream lists,
#: ``tokens_dir`` or ``ablation``, so adding a stream or choosing a grid does not retrain every
#: tokenizer (and, through their rewritten outputs, everything downstream).
TOKENIZER_VQVAE_KEYS = ("model", "families", "loss", "optim", "train", "diagnostics", "metrics", "eval",
                        "trainer", "out_dir", "resume_dir")
TOKENIZER_STREAM_KEY = "vqvae.tokenizers.${item}"


def tokenizer_params() -> list[str]:
    """dvc.yaml's ``params:`` of a tokenizer stage (``foreach`` item: the stream)."""
    return ["seed", *(f"vqvae.{k}" for k in TOKENIZER_VQVAE_KEYS), TOKENIZER_STREAM_KEY, "trainer", "dataset.parts"]
