"""Network slimming (docs/design.md section 11), in four files: ``penalty`` (step 1), ``channels`` (the groups of
step 2), ``prune`` (selection, surgery, checkpoints and budgets) and ``channel_surgery`` (slicing one module):
BatchNorm-scale sparsity, global channel selection, real surgery.

Three steps, as in Liu et al. (2017) and the paper:

1. **Sparsity training**: :func:`slimming_penalty` is the L1 norm of every BatchNorm scale (dense
   ``BatchNorm1d/2d/3d`` and the sparse :class:`models.sparse.BatchNorm`); the trainers add
   ``lambda * penalty`` to the loss (``--slim-lambda``, 1e-4 by default when slimming).
2. **Selection**: :func:`trace_channels` describes a model as *channel groups*: sets of channels that
   must be kept or removed together because they are one index space of the network (a conv's
   output, its BatchNorm, the depthwise conv and squeeze-excite that act on it, every consumer's input
   slice, and everything a residual sum or a BiFPN fusion adds into it). A group channel's importance
   is the largest ``|gamma|`` over the group's BatchNorms (a tied channel is only removed when every
   BatchNorm carrying it says so). One global threshold over all groups removes the ``ratio`` least
   important channels (:func:`select_channels`), or the ratio is searched for a params/MACs budget
   (:func:`prune_checkpoint` with ``params=`` or ``macs=``). A group never loses its last
   ``min_channels`` channels; groups without a BatchNorm (detector heads, SE bottlenecks, transposed convs
   of the baselines, ASPP image pooling) are kept whole.
3. **Surgery**: :func:`prune_model` slices every weight, bias and running statistic of the members
   along the kept indices (concatenated inputs, as in U-Net skips and the multi-view decoders, take
   each part's kept indices at its offset), giving a genuinely narrower network, not a mask.

**Architecture travels with the checkpoint.** A pruned model is described by its builder's config plus
a ``channels`` table ``{module path: [in, out]}`` (``[n]`` for a BatchNorm) holding the layers whose
shape differs from the default build (:func:`channel_table`). Every registered builder takes
``channels=`` and, when given, narrows the default model with :func:`apply_channel_table` (which also
keeps depthwise convs depthwise); nothing else in the forward code depends on widths, and residual
shortcut types are decided by the default build, so a block whose pruned input and output widths
happen to match keeps its projection. :func:`prune_checkpoint` checks the round trip (rebuild from the
config alone, strict ``load_state_dict``) before returning, so a pruned checkpoint loads wherever
checkpoints load (:class:`models.erasenet.model.EraseNet`, the service) and reports its smaller MACs there.

**Torch-Pruning or our own surgery.** Torch-Pruning 1.6 (``BNScalePruner`` with ``regularize()``)
prunes the detector (depthwise, SE and residual ties found by tracing; the BiFPN fusion weights must be
listed in ``ignored_layers``/unwrapped parameters) and, through a custom pruner slicing ``[K, C_in,
C_out]``, our sparse convs (docs/design.md section 11). We wrote the surgery ourselves because:

- Torch-Pruning mutates module objects in place and keeps no description of the result; a checkpoint
  rebuilt by ``create_model(name, **config)`` still needs the ``channels`` table and the code that
  narrows a default build to it, which is most of what the surgery is;
- its graph comes from tracing autograd with example inputs. Our sparse layers run a custom
  ``autograd.Function`` over kernel maps built from coordinates, features travel inside
  ``SparseTensor``/``PointTensor`` containers, and SPVCNN sums point-MLP outputs into devoxelised
  features: each needs custom pruners and example inputs of the right kind, and a tracing miss is a
  silent wrong tie. Here the ties are written once per architecture family from the module structure
  (about 40 lines each), and the exactness tests (zeroed channels removed, outputs unchanged) check them;
- measured here with torch-pruning 1.6.1 (``BNScalePruner``, global ratio 0.4, head outputs ignored): on
  ``centre_detector_tiny`` it pruned 67,335 -> 32,668 params with correct outputs but left the BiFPN at
  its full width (it does not prune through the fusion weights); on ``minkunet_tiny`` its tracer failed
  at once (``'SparseTensor' object has no attribute 'grad_fn'``) before any custom pruner could help;
- no new dependency in the service image, and the same code serves the trainers' L1 penalty.

The cost is that a new architecture needs its tracer (:data:`TRACERS`, named by the class's
``channel_tracer``: :mod:`models.capabilities`); :func:`trace_channels` refuses a model it does not know
instead of guessing.
"""
