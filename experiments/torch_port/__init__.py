"""The PyTorch port of csf_jax's CSF online step, the benchmark's baseline (``experiments.bench``).

``experiments.torch_port.csf`` computes the same math as ``csf_jax.filter`` with the learned prior
(propagate, encode, the step's prior inflation, L reverse steps of either sampler), written as a
PyTorch user would: ``nn.Module`` networks loaded from csf_jax's parameters, eager or
``torch.compile``-d reverse steps, on any torch device. ``tests/test_torch_equivalence.py`` checks
it against csf_jax with the same weights and draws.
"""
