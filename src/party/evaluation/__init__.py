"""Evaluation: T2M evaluators, standard / part-level / coherence / physics metrics, reports.

- ``evaluator``   Guo et al. 2022 text and motion encoders (reference-compatible) + ``Evaluator``
- ``checkpoint``  save/load trained evaluators and the published ``finest.tar``
- ``text_input``  word vectors + POS one-hot (GloVe, offline-encoder word table, contextual tokens)
- ``lit``         LightningModules: movement autoencoder pre-training, contrastive matching
- ``metrics``     R-Precision (any B), FID, MM-Dist, Diversity, MultiModality, MPJPE (vectorised)
- ``coherence``   Temporal / Spatial Coherence (SPEC §5)
- ``physics``     foot skating, floating, ground penetration, jitter (PhysDiff, GMD, TransPose)
- ``stats``       replications, mean ± 95% CI
- ``sources``     ground truth, tokenizer reconstructions, generated runs
- ``protocol``    the replication loop over sources x evaluators
- ``efficiency``  parameter counts, average inference time
- ``report``      Markdown tables (paper Tables 1-5, S3-S5, physical plausibility)
- ``calibrate``   TC/SC hyperparameter calibration against corrupted motions
"""
