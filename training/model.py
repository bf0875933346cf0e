"""LeanGate-S: a small siamese pair model predicting tau = 1 - S (MASt3R-SLAM keyframe score).

  encoder (shared, one image)   3x120x160 -> features 96 x 8 x 10 (stride 16) -- ~0.06 GFLOP
  head (pair)                   global cost volume between the two 80-cell feature grids (cosine,
                                learned temperature), read from both sides: for each current cell the
                                80 similarities to every reference cell (+ its max) -> small CNN ->
                                "is this current cell matched, and where" (f_m-like); the same from the
                                reference side (f_u-like); pooled -> 8-d latent refined in 4 iterations
                                (GRU-style update, paper-like), tau = sigmoid(readout(latent)).
Input RGB in [0,1] normalised outside the graph by the element: (x - MEAN) / STD.
That is the shipped `s16`; `LeanGateS("s8")` is a candidate with 64 channels on a 15x20 grid (stride 8)
and a 1x1 reduction of the 300-cell cost volume in the head (0.20 GFLOP; not shipped, training/experiments/NOTEBOOK.md).
"""
import torch
import torch.nn as nn
import torch.nn.functional as F

from .config import IN_H, IN_W, MEAN, STD  # noqa: F401  (re-exported)

LATENT = 8
ITERS = 4


def conv_bn(cin, cout, stride=1):
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class Encoder(nn.Module):
    """stride 16 (the shipped `s16`): 96 channels on an 8x10 grid; stride 8 (`s8`): 64 on 15x20."""

    def __init__(self, width=(16, 32, 48, 96), stride=16):
        super().__init__()
        c1, c2, c3, c4 = width
        self.net = nn.Sequential(
            conv_bn(3, c1, 2),  # 60x80
            conv_bn(c1, c2, 2),  # 30x40
            conv_bn(c2, c3, 2),  # 15x20
            conv_bn(c3, c3),
            conv_bn(c3, c4, 2 if stride == 16 else 1),  # 8x10 (s16) or 15x20 (s8)
            conv_bn(c4, c4),
            nn.Conv2d(c4, c4, 1),
        )
        self.out_channels = c4

    def forward(self, x):
        return self.net(x)


class Head(nn.Module):
    def __init__(self, c=96, grid=(8, 10), hidden=64, reduce=False):
        super().__init__()
        self.gh, self.gw = grid
        n = self.gh * self.gw
        self.logit_scale = nn.Parameter(torch.tensor(2.3))  # exp -> temperature ~10

        # read the cost volume from the current side (channels = reference cells) and the reference side;
        # `reduce` (the s8 grid's 300 cells) first maps the cells to `hidden` channels with a 1x1 conv
        def side_net():
            if reduce:
                return nn.Sequential(nn.Conv2d(n + 2, hidden, 1), nn.ReLU(inplace=True),
                                     nn.Conv2d(hidden, hidden, 3, 1, 1), nn.ReLU(inplace=True),
                                     nn.Conv2d(hidden, hidden, 3, 1, 1), nn.ReLU(inplace=True))
            return nn.Sequential(nn.Conv2d(n + 2, hidden, 3, 1, 1), nn.ReLU(inplace=True),
                                 nn.Conv2d(hidden, hidden, 3, 1, 1), nn.ReLU(inplace=True))

        self.cur_net = side_net()
        self.ref_net = side_net()
        self.ctx = nn.Sequential(nn.Linear(4 * hidden, 128), nn.ReLU(inplace=True), nn.Linear(128, 64), nn.ReLU(inplace=True))
        # iterative refinement of an 8-d latent (4 iterations)
        self.init = nn.Linear(64, LATENT)
        self.upd_in = nn.Linear(64 + LATENT + 1, 64)
        self.upd_z = nn.Linear(64, LATENT)
        self.upd_r = nn.Linear(64, LATENT)
        self.upd_h = nn.Linear(64, LATENT)
        self.readout = nn.Linear(LATENT, 1)

    def side(self, corr, net, n):
        # corr: [N, cells_this_side, cells_other_side]; softmax-sharpened row max as extra channels
        mx = corr.max(dim=2, keepdim=True).values
        sm = torch.softmax(corr * 2.0, dim=2).max(dim=2, keepdim=True).values
        x = torch.cat([corr, mx, sm], 2)  # [N, n, n+2]
        x = x.transpose(1, 2).reshape(-1, n + 2, self.gh, self.gw)
        y = net(x)
        return torch.cat([y.mean(dim=(2, 3)), y.amax(dim=(2, 3))], 1)

    def forward(self, fr, fc, all_iters=False):
        n = self.gh * self.gw
        # centre each image's features over its cells: ReLU-biased features otherwise make every
        # cosine similarity high (uninformative); also removes global brightness
        r = fr.flatten(2)
        q = fc.flatten(2)
        r = F.normalize(r - r.mean(dim=2, keepdim=True), dim=1)
        q = F.normalize(q - q.mean(dim=2, keepdim=True), dim=1)
        corr = torch.matmul(q.transpose(1, 2), r) * self.logit_scale.exp()  # [N, cur, ref]
        g = torch.cat([self.side(corr, self.cur_net, n), self.side(corr.transpose(1, 2), self.ref_net, n)], 1)
        g = self.ctx(g)
        z = torch.tanh(self.init(g))
        logit = self.readout(z)
        outs = [logit]
        for _ in range(ITERS):
            h = torch.relu(self.upd_in(torch.cat([g, z, torch.sigmoid(logit)], 1)))
            u = torch.sigmoid(self.upd_z(h))
            rr = torch.sigmoid(self.upd_r(h))
            cand = torch.tanh(self.upd_h(h) + rr * z)
            z = (1 - u) * z + u * cand
            logit = logit + self.readout(z)
            outs.append(logit)
        if all_iters:
            return [torch.sigmoid(o).reshape(-1) for o in outs]
        return torch.sigmoid(logit).reshape(-1)


ARCHS = ("s16", "s8")


class LeanGateS(nn.Module):
    def __init__(self, arch="s16"):
        super().__init__()
        if arch not in ARCHS:
            raise ValueError(f"unknown architecture {arch!r} (one of {ARCHS})")
        self.arch = arch
        if arch == "s16":
            self.encoder = Encoder()
            self.head = Head(self.encoder.out_channels)
        else:
            self.encoder = Encoder(width=(16, 32, 48, 64), stride=8)
            self.head = Head(self.encoder.out_channels, grid=(15, 20), reduce=True)

    @staticmethod
    def from_checkpoint(ck):
        """The model a training checkpoint holds (checkpoints before `arch` existed are s16)."""
        m = LeanGateS(ck.get("arch", "s16"))
        m.load_state_dict(ck["model"])
        return m

    def forward(self, reference, current, all_iters=False):
        f = self.encoder(torch.cat([reference, current], 0))
        fr, fc = f[: reference.shape[0]], f[reference.shape[0]:]
        return self.head(fr, fc, all_iters)


class PairWrapper(nn.Module):
    def __init__(self, m):
        super().__init__()
        self.m = m

    def forward(self, reference, current):
        return self.m.head(self.m.encoder(reference), self.m.encoder(current))


def load_onnx_weights(model, encoder_onnx, head_onnx):
    """Load the weights of an exported split model (e.g. the shipped models/leangate-s-*.onnx) into
    `model`, for fine-tuning when no PyTorch checkpoint is at hand. The exporter folded each
    BatchNorm into its convolution, so the BatchNorms become identities (weight 1, bias = the folded
    bias, running mean 0, running variance 1 - eps): keep them in eval mode (`freeze_bn`) while training."""
    import onnx
    from onnx import numpy_helper

    sd = model.state_dict()
    enc = onnx.load(encoder_onnx)
    init = {i.name: numpy_helper.to_array(i) for i in enc.graph.initializer}
    convs = [n for n in enc.graph.node if n.op_type == "Conv"]
    layers = [m for m in model.encoder.net]
    assert len(convs) == len(layers), (len(convs), len(layers))
    new = {}
    for k, (node, layer) in enumerate(zip(convs, layers)):
        w = torch.from_numpy(init[node.input[1]].copy())
        b = torch.from_numpy(init[node.input[2]].copy())
        if isinstance(layer, nn.Conv2d):
            new[f"encoder.net.{k}.weight"], new[f"encoder.net.{k}.bias"] = w, b
        else:
            bn = layer[1]
            new[f"encoder.net.{k}.0.weight"] = w
            new[f"encoder.net.{k}.1.weight"] = torch.ones_like(b)
            new[f"encoder.net.{k}.1.bias"] = b
            new[f"encoder.net.{k}.1.running_mean"] = torch.zeros_like(b)
            new[f"encoder.net.{k}.1.running_var"] = torch.full_like(b, 1.0 - bn.eps)
    head = onnx.load(head_onnx)
    for i in head.graph.initializer:
        key = i.name[2:] if i.name.startswith("m.") else i.name
        if key in sd:
            new[key] = torch.from_numpy(numpy_helper.to_array(i).copy()).reshape(sd[key].shape)
    missing = [k for k in sd if k not in new and not k.endswith("num_batches_tracked")]
    if missing:
        raise ValueError(f"weights not found in the ONNX files: {missing}")
    sd.update(new)
    model.load_state_dict(sd)
    return model


def freeze_bn(model):
    for m in model.modules():
        if isinstance(m, nn.BatchNorm2d):
            m.eval()


def count_flops(model):
    """MACs*2 of conv/linear/matmul for the encoder on one image and the head on one pair."""
    flops = {"encoder": 0, "head": 0}
    hooks = []

    def mk(part):
        def hook(mod, inp, out):
            if isinstance(mod, nn.Conv2d):
                k = mod.kernel_size[0] * mod.kernel_size[1] * mod.in_channels // mod.groups
                flops[part] += 2 * k * out.numel()
            elif isinstance(mod, nn.Linear):
                flops[part] += 2 * mod.in_features * out.numel()
        return hook

    for part, sub in (("encoder", model.encoder), ("head", model.head)):
        for m in sub.modules():
            if isinstance(m, (nn.Conv2d, nn.Linear)):
                hooks.append(m.register_forward_hook(mk(part)))
    model.eval()
    with torch.no_grad():
        x = torch.zeros(1, 3, IN_H, IN_W)
        f = model.encoder(x)
        model.head(f, f)
    for h in hooks:
        h.remove()
    n = model.head.gh * model.head.gw
    flops["head"] += 2 * n * n * model.encoder.out_channels  # cost volume matmul
    return flops
