"""The benchmark kit: generated scenes with known ground truth, scoring against it, evaluation, baselines and
training helpers. The library (everything else in ``nerfuser_ns``) never imports it."""
