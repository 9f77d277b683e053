"""Tests for LRGT: grouping attention, the encoder's dropped prefix tokens, Dice loss, the network and LightningModule.

The merger and the decoder have their own files (``test_lrgt_merger.py``, ``test_lrgt_decoder.py``).
"""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
import torch.nn.functional as F

from lightning_vtr.models.lrgt import (
    LRGT,
    LRGT_PRESETS,
    LongRangeGroupingAttention,
    LRGTNetwork,
    LRGTSpec,
    dice_loss,
)

DIM, HEADS, GRID, STRIDE = 8, 2, 4, 2


@pytest.fixture(autouse=True)
def one_thread():
    """Run single-threaded: on 2 shared cores, 2 threads per process oversubscribe badly (10x slower)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _attend(attn: LongRangeGroupingAttention, tokens: torch.Tensor) -> torch.Tensor:
    """Plain multi-head softmax attention of a token list ``(T, D)`` with attn's qkv, before proj."""
    q, k, v = attn.qkv(tokens).split(DIM, dim=-1)
    hd = DIM // HEADS
    out = []
    for h in range(HEADS):
        sl = slice(h * hd, (h + 1) * hd)
        out.append(torch.softmax(q[:, sl] @ k[:, sl].T / math.sqrt(hd), dim=-1) @ v[:, sl])
    return torch.cat(out, dim=-1)


def _reference_grouping_attention(attn: LongRangeGroupingAttention, x: torch.Tensor, views: int) -> torch.Tensor:
    """Loop over groups: gather each group's tokens across views, attend, scatter back."""
    bv, _t, _ = x.shape
    out = torch.zeros_like(x)
    for b in range(bv // views):
        rows = range(b * views, (b + 1) * views)
        for a in range(STRIDE):
            for c in range(STRIDE):
                members = [
                    (r, row * GRID + col)
                    for r in rows
                    for row in range(GRID)
                    for col in range(GRID)
                    if row % STRIDE == a and col % STRIDE == c
                ]
                res = _attend(attn, torch.stack([x[r, p] for r, p in members]))
                for n, (r, p) in enumerate(members):
                    out[r, p] = res[n]
    # signature: depthwise 3x3 (zero padded) conv of each view's value map, written as a neighbour sum
    values = attn.qkv(x)[..., 2 * DIM :]
    w, bias = attn.signature.weight[:, 0], attn.signature.bias
    for r in range(bv):
        for row in range(GRID):
            for col in range(GRID):
                s = bias.clone()
                for dr in (-1, 0, 1):
                    for dc in (-1, 0, 1):
                        rr, cc = row + dr, col + dc
                        if 0 <= rr < GRID and 0 <= cc < GRID:
                            s = s + w[:, dr + 1, dc + 1] * values[r, rr * GRID + cc]
                out[r, row * GRID + col] += s
    return attn.proj(out)


def _random_grouping_attention() -> LongRangeGroupingAttention:
    torch.manual_seed(0)
    attn = LongRangeGroupingAttention(DIM, HEADS, GRID, STRIDE)
    # The signature starts at zero; make it matter for the comparison.
    torch.nn.init.normal_(attn.signature.weight)
    torch.nn.init.normal_(attn.signature.bias)
    return attn


@pytest.mark.parametrize("views", [1, 3])
def test_grouping_attention_equals_loop_reference(views):
    attn = _random_grouping_attention()
    x = torch.randn(2 * views, GRID * GRID, DIM)
    with torch.no_grad():
        expected = _reference_grouping_attention(attn, x, views)
        actual = attn(x, num_views=views)
    assert torch.allclose(actual, expected, atol=1e-5)


def test_grouping_attention_one_view_is_per_view_and_views_do_mix_otherwise():
    attn = _random_grouping_attention()
    x = torch.randn(3, GRID * GRID, DIM)
    with torch.no_grad():
        alone = torch.cat([attn(x[i : i + 1], num_views=1) for i in range(3)])
        # Three separate 1-view samples equal one batch of three 1-view samples ...
        assert torch.allclose(attn(x, num_views=1), alone, atol=1e-6)
        # ... but not one 3-view sample, whose groups span the views.
        assert not torch.allclose(attn(x, num_views=3), alone, atol=1e-3)
        # Group (0, 0) of the single view is patches (0,0), (0,2), (2,0), (2,2): perturbing patch
        # (1, 1) (group (1, 1)) changes no group-(0,0) output except via the signature of its
        # 3x3 neighbours (0,0), (0,2), (2,0), (2,2) -- so zero the signature to isolate groups.
        torch.nn.init.zeros_(attn.signature.weight)
        y = x[:1].clone()
        y[0, 1 * GRID + 1] += 5.0
        before, after = attn(x[:1], 1), attn(y, 1)
        group00 = [r * GRID + c for r in (0, 2) for c in (0, 2)]
        assert torch.allclose(before[0, group00], after[0, group00], atol=1e-6)
        assert not torch.allclose(before[0, 1 * GRID + 3], after[0, 1 * GRID + 3], atol=1e-3)


def test_grouping_attention_rejects_bad_stride_and_shapes():
    with pytest.raises(ValueError, match="group_stride"):
        LongRangeGroupingAttention(DIM, HEADS, grid_size=14, group_stride=4)
    attn = LongRangeGroupingAttention(DIM, HEADS, GRID, STRIDE)
    with pytest.raises(ValueError, match=r"`x` must be \(B \* 2, 16, D\) patch tokens, got \(3, 16, 8\)"):
        attn(torch.randn(3, GRID * GRID, DIM), num_views=2)
    with pytest.raises(ValueError, match=r"`x` must be \(B \* 1, 16, D\) patch tokens, got \(1, 18, 8\)"):
        attn(torch.randn(1, 2 + GRID * GRID, DIM))  # cls/dist tokens are dropped before the blocks


def test_paper_grouping_layout_is_49_groups_of_4_tokens_per_view():
    attn = LongRangeGroupingAttention(12, 2, grid_size=14, group_stride=7)
    index = torch.arange(14 * 14, dtype=torch.float32).reshape(1, 1, 196, 1).expand(2, 1, 196, 1)
    groups = attn._to_groups(index, num_views=2)  # one sample, two views
    assert groups.shape == (49, 1, 8, 1)
    # group (a, b) = (1, 3): patches (1, 3), (1, 10), (8, 3), (8, 10) of each view.
    members = groups[1 * 7 + 3, 0, :, 0].tolist()
    assert members == [1 * 14 + 3, 1 * 14 + 10, 8 * 14 + 3, 8 * 14 + 10] * 2
    assert torch.equal(attn._from_groups(groups, num_views=2), index)


def test_dice_loss_hand_computed():
    p = torch.tensor([[0.5, 1.0, 0.0, 0.25]])
    t = torch.tensor([[1.0, 1.0, 0.0, 0.0]])
    # sum(pt) = 1.5, sum(p^2) = 0.25 + 1 + 0.0625 = 1.3125, sum(t^2) = 2
    assert dice_loss(p, t).item() == pytest.approx(1 - 2.5 / 4.3125)
    with pytest.raises(ValueError, match="same shape"):
        dice_loss(p, t[:, :3])


def test_network_shapes_any_number_of_views_and_view_order_invariance():
    torch.manual_seed(0)
    net = LRGTNetwork(LRGT_PRESETS["tiny"]).eval()
    for block in net.grouping_blocks:
        torch.nn.init.normal_(net.encoder.blocks[block].attn.signature.weight, std=0.1)
    images = torch.randn(2, 3, 3, 64, 64)
    with torch.no_grad():
        out = net(images)
        assert out.shape == (2, 32, 32, 32)
        assert ((out > 0) & (out < 1)).all()
        for v in (1, 5):
            assert net(torch.randn(2, v, 3, 64, 64)).shape == (2, 32, 32, 32)
        permuted = net(images[:, [2, 0, 1]])
        # 3 views of 64 tokens merge into 64; one view already has 64 tokens, as many as clusters.
        assert net.merger(net.encode(images)).shape == (2, 64, 64)
        assert net.merger(net.encode(images[:, :1])).shape == (2, 64, 64)
    assert torch.allclose(out, permuted, atol=1e-5)
    with pytest.raises(ValueError, match=r"\(B, V, 3, H, W\)"):
        net(torch.randn(2, 3, 64, 64))


def test_fewer_tokens_than_clusters_still_reconstruct():
    # One 8x8-token view and 100 clusters: every token is its own cluster and the decoder reads 64 tokens.
    torch.manual_seed(0)
    net = LRGTNetwork(dataclasses.replace(LRGT_PRESETS["tiny"], num_merged_tokens=100)).eval()
    images = torch.randn(2, 1, 3, 64, 64)
    with torch.no_grad():
        assert net.merger(net.encode(images)).shape == (2, 64, 64)
        out = net(images)
    assert out.shape == (2, 32, 32, 32) and torch.isfinite(out).all()


#: Parameter counts of the released LRGT (LiyingCV/Long-Range-Grouping-Transformer at a09fc43, config.py
#: defaults: DeiT-B distilled, STM 2 x 196 tokens, decoder depth 8), obtained by instantiating its Encoder,
#: Merger and Decoder in a scratch script outside this repository (timm 0.4.5's Mlp, no pretrained download).
#: Its encoder builds the inter-view signature convolution (7,680 parameters) in all 12 blocks but uses
#: it only in blocks 5, 7, 9 and 11; ours builds those 4, hence 8 x 7,680 = 61,440 fewer.
RELEASED_PARAMETERS = {"encoder": 85_892_352, "merger": 14_172_674, "decoder": 29_798_625}


def test_paper_preset_parameter_counts_per_module_match_the_released_code():
    with torch.device("meta"):
        net = LRGTNetwork(LRGT_PRESETS["paper"])
        out = net(torch.empty(2, 3, 3, 224, 224))
    counts = {name: sum(p.numel() for p in getattr(net, name).parameters()) for name in RELEASED_PARAMETERS}
    assert counts == {"encoder": 85_892_352 - 8 * 7_680, "merger": 14_172_674, "decoder": 29_798_625}
    for name, released in RELEASED_PARAMETERS.items():
        assert abs(counts[name] - released) / released < 0.01, (name, counts[name], released)
    assert sum(p.numel() for p in net.parameters()) == 129_802_211
    assert out.shape == (2, 32, 32, 32)
    assert net.encoder.grid_size == 14


def test_encoder_drops_the_prefix_tokens_but_keeps_them_loadable():
    torch.manual_seed(0)
    net = LRGTNetwork(LRGT_PRESETS["tiny"]).eval()
    images = torch.randn(2, 3, 3, 64, 64)
    with torch.no_grad():
        tokens = net.encode(images)
        assert tokens.shape == (2, 3 * 64, 64)  # 8x8 patch tokens per view, nothing else
        assert torch.allclose(
            net.encoder.embed(images[0]), net.encoder.patch_embed(images[0]) + net.encoder.pos_embed[:, 2:]
        )
        out = net(images)
        # cls, dist and their position embeddings take no part in the forward.
        net.encoder.cls_token.normal_()
        net.encoder.dist_token.normal_()
        net.encoder.pos_embed[:, :2].normal_()
        assert torch.equal(net(images), out)
    assert not net.encoder.cls_token.requires_grad and not net.encoder.dist_token.requires_grad
    assert {"encoder.cls_token", "encoder.dist_token"} <= set(net.state_dict())
    assert net.encoder.pos_embed.shape == (1, 2 + 64, 64)


def test_every_trainable_parameter_gets_a_gradient():
    # Distributed training fails on parameters that take no part in the loss; the unused cls/dist tokens are frozen.
    torch.manual_seed(0)
    model = LRGT(preset="tiny")
    target = (torch.rand(2, 32, 32, 32) > 0.7).float()
    model.loss(model(torch.randn(2, 3, 3, 64, 64)), target).backward()
    assert [n for n, p in model.named_parameters() if p.requires_grad and p.grad is None] == []
    assert [n for n, p in model.named_parameters() if not p.requires_grad] == [
        "network.encoder.cls_token",
        "network.encoder.dist_token",
    ]


def test_pretrained_encoder_loads_into_grouping_blocks():
    preset = LRGT_PRESETS["tiny"]
    net = LRGTNetwork(preset)
    own = {k: v for k, v in net.encoder.state_dict().items() if ".signature." not in k}
    state = {k: torch.randn_like(v) for k, v in own.items()} | {"head.weight": torch.zeros(3, 64)}
    net.load_pretrained_encoder(state)
    block = preset.grouping_blocks[0]
    assert torch.equal(net.encoder.blocks[block].attn.qkv.weight, state[f"blocks.{block}.attn.qkv.weight"])
    assert not net.encoder.blocks[block].attn.signature.weight.any()
    for key in ("cls_token", "dist_token", "pos_embed"):
        assert torch.equal(getattr(net.encoder, key), state[key])


def test_pretrained_encoder_from_a_url_and_a_checkpoint_that_loads_without_the_file(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    net = LRGTNetwork(LRGT_PRESETS["tiny"])
    own = {k: v for k, v in net.encoder.state_dict().items() if ".signature." not in k}
    torch.manual_seed(3)
    state = {k: torch.randn_like(v) for k, v in own.items()}
    source = tmp_path / "deit_tiny.pth"
    torch.save({"model": state}, source)
    model = LRGT(preset="tiny", pretrained_encoder=source.as_uri())  # file:// URL through torch.hub's cache
    assert (tmp_path / "torch_home" / "hub" / "checkpoints" / "deit_tiny.pth").is_file()
    assert torch.equal(model.network.encoder.blocks[0].attn.qkv.weight, state["blocks.0.attn.qkv.weight"])
    ckpt = tmp_path / "model.ckpt"
    torch.save(
        {
            "state_dict": model.state_dict(),
            "hyper_parameters": dict(model.hparams),
            "pytorch-lightning_version": "2.5.0",
        },
        ckpt,
    )
    source.unlink()
    (tmp_path / "torch_home" / "hub" / "checkpoints" / "deit_tiny.pth").unlink()
    restored = LRGT.load_from_checkpoint(ckpt)  # the weight file is gone: the checkpoint holds the weights
    assert restored.hparams.pretrained_encoder == source.as_uri()
    for (name, a), (_, b) in zip(model.state_dict().items(), restored.state_dict().items()):
        assert torch.equal(a, b), name
    assert LRGT.image_recipe == "lrgt"


def test_preset_specs_hold_the_published_and_tiny_architectures():
    paper, tiny = LRGT_PRESETS["paper"], LRGT_PRESETS["tiny"]
    assert set(LRGT_PRESETS) == {"paper", "tiny"}
    assert (paper.image_size, paper.patch_size, paper.embed_dim, paper.depth, paper.num_heads) == (224, 16, 768, 12, 12)
    assert paper.grouping_blocks == (5, 7, 9, 11) and paper.group_stride == 7 and paper.grid_size == 14
    assert (paper.num_merged_tokens, paper.merger_k, paper.merger_depth) == (196, 15, 2)
    assert (paper.decoder_depth, paper.decoder_stage_depth, paper.decoder_heads) == (1, 2, 12)
    assert paper.query_grid == 4 and paper.upsample_channels == (96, 12, 3) and paper.voxel_resolution == 32
    assert (tiny.image_size, tiny.patch_size, tiny.embed_dim, tiny.depth, tiny.num_heads) == (64, 8, 64, 4, 4)
    assert tiny.grouping_blocks == (1, 3) and tiny.group_stride == 4 and tiny.grid_size == 8
    assert (tiny.num_merged_tokens, tiny.merger_k, tiny.merger_depth) == (64, 5, 2)
    assert (tiny.decoder_depth, tiny.decoder_stage_depth, tiny.decoder_heads) == (1, 0, 1)
    assert tiny.query_grid == 4 and tiny.upsample_channels == (16, 4, 6) and tiny.voxel_resolution == 32


def test_spec_is_frozen_normalises_sequences_and_compares_by_value():
    tiny = LRGT_PRESETS["tiny"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        tiny.depth = 8
    fields = dataclasses.asdict(tiny)
    from_lists = LRGTSpec(**{**fields, "grouping_blocks": [1, 3], "upsample_channels": [16, 4, 6]})
    assert from_lists.grouping_blocks == (1, 3) and from_lists.upsample_channels == (16, 4, 6)
    assert from_lists == tiny and hash(from_lists) == hash(tiny)
    assert LRGTNetwork(LRGTSpec(**fields)).spec == tiny


@pytest.mark.parametrize(
    ("change", "error", "match"),
    [
        (
            {"grouping_blocks": (1, 4)},
            ValueError,
            r"`grouping_blocks` must be 0-based block indices in \[0, 4\), got \[1, 4\]",
        ),
        ({"grouping_blocks": 3}, TypeError, r"`grouping_blocks` must be a sequence of ints, got int 3"),
        ({"depth": "4"}, TypeError, r"`depth` must be an int, got str '4'"),
        ({"embed_dim": 0}, ValueError, r"`embed_dim` must be an int >= 1, got 0"),
        ({"upsample_channels": (32, 0)}, ValueError, r"`upsample_channels\[1\]` must be an int >= 1, got 0"),
        ({"decoder_depth": 0}, ValueError, r"`decoder_depth` must be an int >= 1, got 0"),
        ({"merger_depth": 0}, ValueError, r"`merger_depth` must be an int >= 1, got 0"),
        ({"decoder_stage_depth": -1}, ValueError, r"`decoder_stage_depth` must be an int >= 0, got -1"),
        ({"num_heads": 3}, ValueError, r"`num_heads` must divide `embed_dim` 64, got 3"),
        (
            {"upsample_channels": (16, 4, 1)},
            ValueError,
            r"`upsample_channels` must end in 2 or more channels when `decoder_stage_depth` is 0: .*got \[16, 4, 1\]",
        ),
        (
            {"decoder_heads": 32},
            ValueError,
            r"`decoder_heads` must divide the decoder stage widths \[16, 32, 384\] \(`upsample_channels` "
            r"\[16, 4, 6\] x patch\^3\), got 32",
        ),
    ],
)
def test_spec_rejects_bad_fields(change, error, match):
    with pytest.raises(error, match=match):
        dataclasses.replace(LRGT_PRESETS["tiny"], **change)


def test_a_decoder_without_stage_blocks_starts_with_a_head_of_both_signs():
    for seed in range(4):
        torch.manual_seed(seed)
        network = LRGTNetwork(LRGT_PRESETS["tiny"])
        assert [len(stage.blocks) for stage in network.decoder.stages] == [0, 0, 0]
        signs = torch.sign(network.decoder.head.weight.flatten()).tolist()
        assert signs == [1.0, -1.0, 1.0, -1.0, 1.0, -1.0]
        # So some voxels start below 0.5: the ReLU features are >= 0, and a head of one sign keeps every
        # probability on one side of 0.5.
        probs = network(torch.randn(2, 3, 3, 64, 64))
        assert (probs < 0.5).any() and (probs > 0.5).any()
    # With stage blocks (the paper's decoder) the head keeps its Kaiming draw as released: signs as drawn.
    with_blocks = dataclasses.replace(LRGT_PRESETS["tiny"], decoder_stage_depth=2)
    patterns = set()
    for seed in range(4):
        torch.manual_seed(seed)
        patterns.add(tuple(torch.sign(LRGTNetwork(with_blocks).decoder.head.weight.flatten()).tolist()))
    assert len(patterns) > 1


def test_model_and_network_are_built_from_the_spec():
    tiny = LRGT_PRESETS["tiny"]
    model = LRGT(preset="tiny")
    assert model.spec == tiny and model.network.spec == tiny
    assert LRGTNetwork(tiny).spec == tiny
    small = LRGT(preset="tiny", image_size=32, patch_size=4, upsample_channels=[16, 8])
    assert small.spec == dataclasses.replace(tiny, image_size=32, patch_size=4, upsample_channels=(16, 8))
    assert (small.spec.grid_size, small.spec.voxel_resolution, small.voxel_resolution) == (8, 16, 16)
    # The hyperparameters (what checkpoints and loggers see) keep their form: lists for the sequences.
    assert small.hparams.upsample_channels == [16, 8] and small.hparams.grouping_blocks == [1, 3]
    with pytest.raises(ValueError, match=r"`grouping_blocks` must be 0-based block indices in \[0, 4\)"):
        LRGT(preset="tiny", grouping_blocks=[7])
    with pytest.raises(ValueError, match=r"`lr` must be a number > 0, got 0.0"):
        LRGT(preset="tiny", lr=0.0)
    with pytest.raises(TypeError, match=r"`spec` must be an LRGTSpec, got dict"):
        LRGTNetwork(dataclasses.asdict(tiny))


def _shapes(r: int) -> torch.Tensor:
    """Three solid shapes ``(3, r, r, r)``: cube, upright cylinder, flat slab."""
    c = (torch.arange(r) + 0.5) / r - 0.5
    x, y, z = torch.meshgrid(c, c, c, indexing="ij")
    return torch.stack(
        [
            (x.abs() < 0.3) & (y.abs() < 0.3) & (z.abs() < 0.3),
            (x**2 + y**2 < 0.2**2) & (z.abs() < 0.4),
            (x.abs() < 0.4) & (y.abs() < 0.1) & (z.abs() < 0.25),
        ]
    ).float()


def test_lightning_module_protocol_and_errors():
    from lightning_vtr.protocol import check_reconstruction_model

    model = LRGT(preset="tiny", num_views=2)
    check_reconstruction_model(model)
    assert (model.image_size, model.num_views, model.voxel_resolution) == (64, 2, 32)
    assert model.hparams.preset == "tiny" and model.hparams.lr == 1e-4
    small = LRGT(preset="tiny", image_size=32, patch_size=4, upsample_channels=[16, 8])
    assert (small.image_size, small.voxel_resolution) == (32, 16)
    opt = small.configure_optimizers()
    assert isinstance(opt["optimizer"], torch.optim.AdamW)
    assert opt["lr_scheduler"]["scheduler"].milestones == {60: 1, 90: 1}
    with pytest.raises(ValueError, match="`preset` must be one of"):
        LRGT(preset="huge")
    with pytest.raises(ValueError, match="32x32"):
        small.predict_voxels(torch.randn(1, 3, 3, 64, 64))


@pytest.mark.slow
def test_overfits_a_handful_of_objects_with_a_trainer():
    import lightning as L
    from torch.utils.data import DataLoader

    # The tiny preset at 32 px in, 16^3 out keeps this test to seconds on 2 shared cores.
    voxels = _shapes(16)
    n = len(voxels)
    # Fixed distinct images per object: its silhouettes along x, y and z as the three views.
    silhouettes = torch.stack([voxels.amax(dim=d) for d in (1, 2, 3)], dim=1)
    images = F.interpolate(silhouettes, size=32)[:, :, None].expand(n, 3, 3, 32, 32) * 2 - 1
    # ... tinted with a colour per object, like the distinct textures of real objects.
    images = images * torch.eye(3)[:, None, :, None, None].add(0.5)
    data = [{"images": images[i], "voxels": voxels[i], "category": "shape", "object_id": str(i)} for i in range(n)]
    # 120 epochs leave a margin: with this recipe seed 0 reaches IoU 1.0 on every shape by epoch 100.
    torch.manual_seed(0)
    model = LRGT(
        preset="tiny",
        image_size=32,
        patch_size=4,
        upsample_channels=[16, 8],
        lr=2e-3,
        milestones=[90],
        validation_fscore=False,
    )
    trainer = L.Trainer(
        max_epochs=120,
        accelerator="cpu",
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        limit_val_batches=0,
    )
    trainer.fit(model, DataLoader(data, batch_size=n))
    model.eval()
    with torch.no_grad():
        pred = model.predict_voxels(images) >= 0.4
    gt = voxels.bool()
    iou = (pred & gt).sum((1, 2, 3)) / (pred | gt).sum((1, 2, 3))
    assert (iou >= 0.9).all(), iou


def test_checkpoint_round_trip_records_the_resolved_architecture(tmp_path):
    model = LRGT(preset="tiny", embed_dim=32, num_heads=2)
    assert model.hparams.image_size == 64 and model.hparams.grouping_blocks == [1, 3]
    assert model._hparams_initial["image_size"] == 64  # what Lightning logs and merges
    path = tmp_path / "lrgt.pt"
    torch.save({"state_dict": model.state_dict(), "hparams": dict(model.hparams)}, path)
    saved = torch.load(path, weights_only=False)
    restored = LRGT(**saved["hparams"])
    restored.load_state_dict(saved["state_dict"])
    images = torch.randn(1, 2, 3, 64, 64)
    model.eval(), restored.eval()
    with torch.no_grad():
        assert torch.equal(model.predict_voxels(images), restored.predict_voxels(images))


#: The ``hyper_parameters`` a Trainer stored for ``LRGT(preset="tiny", image_size=32, patch_size=4, embed_dim=32,
#: num_heads=2, upsample_channels=[16, 8])`` when ``LRGTNetwork`` took the 15 spec fields as arguments and the
#: tiny decoder had two attention blocks per stage (0.3): every architecture field resolved, the sequences as lists.
SAVED_HPARAMS = {
    "preset": "tiny",
    "num_views": 3,
    "image_size": 32,
    "patch_size": 4,
    "embed_dim": 32,
    "depth": 4,
    "num_heads": 2,
    "grouping_blocks": [1, 3],
    "group_stride": 4,
    "num_merged_tokens": 64,
    "merger_k": 5,
    "merger_depth": 2,
    "decoder_depth": 1,
    "decoder_stage_depth": 2,
    "decoder_heads": 1,
    "query_grid": 4,
    "upsample_channels": [16, 8],
    "pretrained_encoder": None,
    "lr": 0.0001,
    "weight_decay": 0.01,
    "milestones": None,
    "gamma": 0.1,
    "validation_fscore": True,
    "log_sheets": 0,
    "categories": None,
}
#: sha256 of the ``"name:(shape)"`` lines of that checkpoint's state dict (186 tensors), in state-dict order.
SAVED_STATE_LAYOUT = "e4f2b93656aab7f4341ffb26055725f0b7b0556886f6bbe58ed5c30111897a21"


def test_checkpoints_saved_with_the_spec_fields_as_hparams_load_and_predict_the_same(tmp_path):
    import hashlib

    overrides = {
        k: SAVED_HPARAMS[k] for k in ("image_size", "patch_size", "embed_dim", "num_heads", "upsample_channels")
    }
    torch.manual_seed(0)
    model = LRGT(preset="tiny", decoder_stage_depth=2, **overrides).eval()  # 0.3's tiny decoder
    # The state dict keeps its layout and the hyperparameters their form ...
    state = model.state_dict()
    layout = "\n".join(f"{k}:{tuple(v.shape)}" for k, v in state.items())
    assert (len(state), hashlib.sha256(layout.encode()).hexdigest()) == (186, SAVED_STATE_LAYOUT)
    assert dict(model.hparams) == SAVED_HPARAMS and list(model.hparams) == list(SAVED_HPARAMS)
    # ... so a checkpoint of that form loads and predicts exactly what the saved model did.
    path = tmp_path / "lrgt.ckpt"
    torch.save(
        {
            "state_dict": state,
            "hyper_parameters": dict(SAVED_HPARAMS),
            "hparams_name": "kwargs",
            "pytorch-lightning_version": "2.5.0",
        },
        path,
    )
    restored = LRGT.load_from_checkpoint(path).eval()
    assert restored.spec == dataclasses.replace(LRGT_PRESETS["tiny"], **overrides, decoder_stage_depth=2)
    assert restored.spec.upsample_channels == (16, 8) and restored.spec.embed_dim == 32
    assert LRGT_PRESETS["tiny"].decoder_stage_depth == 0  # the checkpoint, not the preset, gave the two blocks
    images = torch.randn(2, 3, 3, 32, 32)
    with torch.no_grad():
        assert torch.equal(restored.predict_voxels(images), model.predict_voxels(images))


def test_the_optimizer_is_torchs_fused_adamw_and_steps_like_the_looped_one():
    # The decoder's upsampling weights are channels_last_3d: the fused step must update them element for element
    # as the per-parameter loop does (autograd hands each parameter a gradient in its own layout).
    torch.manual_seed(0)
    fused = LRGT(preset="tiny")
    looped = LRGT(preset="tiny")
    looped.load_state_dict(fused.state_dict())
    start = {name: p.detach().clone() for name, p in fused.named_parameters()}
    assert fused.network.decoder.stages[-1].upsample[0].weight.is_contiguous(memory_format=torch.channels_last_3d)
    fused_opt = fused.configure_optimizers()["optimizer"]
    assert isinstance(fused_opt, torch.optim.AdamW) and fused_opt.defaults["fused"] is True
    looped_opt = torch.optim.AdamW(looped.parameters(), lr=fused.hparams.lr, weight_decay=fused.hparams.weight_decay)
    images, voxels = torch.randn(2, 3, 3, 64, 64), (torch.rand(2, 32, 32, 32) > 0.7).float()
    for model, opt in ((fused, fused_opt), (looped, looped_opt)):
        for _ in range(2):
            opt.zero_grad()
            model.loss(model(images), voxels).backward()
            opt.step()
    moved = 0
    for (name, a), b in zip(fused.named_parameters(), looped.parameters(), strict=True):
        torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-5, msg=name)
        moved += int(not torch.equal(a, start[name]))
    assert moved == sum(p.requires_grad for p in fused.parameters())  # every trained weight moved
