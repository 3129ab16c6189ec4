"""TensorFlow.js Keras layers-models -> a torch graph module and a safetensors file.

Supported graph (everything else is refused with a clear error): ``InputLayer``; ``Conv2D``
(stride 1, dilation 1, ``same`` padding, odd square kernel, channels-last, bias, activation
linear or relu); ``Activation`` relu/linear; ``Concatenate`` on the channel axis; ``Add``;
UpscalerJS's custom ``MultiplyBeta`` (x0.2; the beta is hard-coded in UpscalerJS's JS layer,
not stored in model.json) and ``PixelShuffle{s}x`` (``tf.depthToSpace(x, s, 'NHWC')``).

TF's ``depth_to_space`` reads input channel ``(i*s + j)*C + c`` for output pixel offset (i, j)
and channel c; torch's ``pixel_shuffle`` reads ``c*s*s + i*s + j``. :func:`depth_to_space`
implements TF's order (the wrong one gives a colour-shifted mess).

Weights: ``weightsManifest`` lists tensors in order, concatenated across the shard files,
float32 little-endian. Conv kernels are (kh, kw, in, out) and become torch's (out, in, kh, kw).

The converted file stores the tensors as ``<layer>.weight``/``<layer>.bias`` and the graph (a
JSON list of ops) in the safetensors metadata, so loading reads only that file.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from safetensors.torch import load_file, save_file
from torch import nn

FORMAT = "pbrsr-tfjs-graph-v1"


class TfjsConversionError(ValueError):
    """The TF.js model uses something this converter does not support."""


def depth_to_space(x: torch.Tensor, s: int) -> torch.Tensor:
    """TF's NHWC ``depth_to_space`` on an NCHW tensor: x (N, s*s*C, H, W) -> (N, C, s*H, s*W),
    output[n, c, h*s + i, w*s + j] = x[n, (i*s + j)*C + c, h, w]."""
    n, cin, h, w = x.shape
    c = cin // (s * s)
    if c * s * s != cin:
        raise ValueError(f"depth_to_space: {cin} channels is not a multiple of {s * s}")
    x = x.reshape(n, s, s, c, h, w).permute(0, 3, 4, 1, 5, 2)
    return x.reshape(n, c, h * s, w * s)


def _inputs(layer: dict) -> list[str]:
    nodes = layer.get("inbound_nodes") or []
    if len(nodes) > 1:
        raise TfjsConversionError(f"layer {layer['name']!r} is shared; not supported")
    return [entry[0] for entry in nodes[0]] if nodes else []


def parse_graph(model_json: dict) -> tuple[list[dict], dict[str, tuple[int, ...]]]:
    """Graph ops in topological (file) order and the conv kernel shapes by layer name.

    Each op is ``{"op": kind, "name": str, "inputs": [names], ...}`` with kind one of
    input, conv (+ ``relu``: bool), relu, concat, add, mul (+ ``factor``), d2s (+ ``scale``),
    identity. The last op is the model output."""
    if model_json.get("format") != "layers-model":
        raise TfjsConversionError(f"not a TF.js layers-model: format {model_json.get('format')!r}")
    topo = model_json["modelTopology"]
    cfg = topo.get("model_config", topo)["config"]
    ops: list[dict] = []
    kernels: dict[str, tuple[int, ...]] = {}
    for layer in cfg["layers"]:
        kind, name, c = layer["class_name"], layer["name"], layer["config"]
        ins = _inputs(layer)
        if kind == "InputLayer":
            shape = c.get("batch_input_shape") or c.get("batchInputShape")
            if shape is None or shape[-1] != 3:
                raise TfjsConversionError(f"input {name!r} must be channels-last RGB: {shape}")
            ops.append({"op": "input", "name": name, "inputs": []})
        elif kind == "Conv2D":
            ks, st = tuple(c["kernel_size"]), tuple(c.get("strides", (1, 1)))
            dil = tuple(c.get("dilation_rate", (1, 1)))
            if (
                c.get("padding") != "same"
                or st != (1, 1)
                or dil != (1, 1)
                or ks[0] != ks[1]
                or ks[0] % 2 != 1
                or c.get("data_format", "channels_last") != "channels_last"
                or not c.get("use_bias", True)
                or c.get("groups", 1) != 1
                or c.get("activation") not in ("linear", "relu")
            ):
                raise TfjsConversionError(f"unsupported Conv2D configuration in {name!r}")
            ops.append(
                {"op": "conv", "name": name, "inputs": ins, "relu": c["activation"] == "relu"}
            )
            kernels[name] = ks
        elif kind == "Activation":
            act = c.get("activation")
            if act not in ("relu", "linear"):
                raise TfjsConversionError(f"unsupported activation {act!r} in {name!r}")
            ops.append({"op": "relu" if act == "relu" else "identity", "name": name, "inputs": ins})
        elif kind == "Concatenate":
            if c.get("axis") not in (-1, 3):
                raise TfjsConversionError(f"concatenation on axis {c.get('axis')} in {name!r}")
            ops.append({"op": "concat", "name": name, "inputs": ins})
        elif kind == "Add":
            ops.append({"op": "add", "name": name, "inputs": ins})
        elif kind == "MultiplyBeta":
            ops.append({"op": "mul", "name": name, "inputs": ins, "factor": 0.2})
        elif kind.startswith("PixelShuffle") and kind.endswith("x") and kind[12:-1].isdigit():
            ops.append({"op": "d2s", "name": name, "inputs": ins, "scale": int(kind[12:-1])})
        else:
            raise TfjsConversionError(f"unsupported layer class {kind!r} ({name!r})")
    outputs = cfg["output_layers"]
    if len(outputs) != 1 or outputs[0][0] != ops[-1]["name"]:
        raise TfjsConversionError("the model must have a single output, its last layer")
    if len(cfg["input_layers"]) != 1 or ops[0]["op"] != "input":
        raise TfjsConversionError("the model must have a single input, its first layer")
    known: set[str] = set()
    for op in ops:
        missing = [i for i in op["inputs"] if i not in known]
        if missing:
            raise TfjsConversionError(f"layer {op['name']!r} uses {missing} before definition")
        known.add(op["name"])
    return ops, kernels


def read_weights(model_dir: Path, model_json: dict) -> dict[str, np.ndarray]:
    """The float32 tensors of ``weightsManifest``, by Keras name (e.g. ``F_1_1_1/kernel``)."""
    out: dict[str, np.ndarray] = {}
    for group in model_json["weightsManifest"]:
        blob = b"".join((model_dir / p).read_bytes() for p in group["paths"])
        offset = 0
        for spec in group["weights"]:
            if spec.get("dtype") != "float32" or "quantization" in spec:
                raise TfjsConversionError(f"weight {spec['name']!r} is not plain float32")
            count = int(np.prod(spec["shape"])) if spec["shape"] else 1
            nbytes = count * 4
            if offset + nbytes > len(blob):
                raise TfjsConversionError("the weight shards are shorter than the manifest")
            arr = np.frombuffer(blob, dtype="<f4", count=count, offset=offset)
            out[spec["name"]] = arr.reshape(spec["shape"]).astype(np.float32)
            offset += nbytes
        if offset != len(blob):
            raise TfjsConversionError("the weight shards are longer than the manifest")
    return out


class TfjsGraphNet(nn.Module):
    """A torch module that runs a parsed TF.js graph on NCHW tensors. ``forward`` takes
    (N, 3, H, W) and returns the output layer's tensor; intermediate tensors are freed after
    their last use, so peak memory stays near the widest concatenation.

    Activations run channels-last (NHWC, oneDNN's and cuDNN's native layout): rrdn-thick at x4
    on a 256² input took 4.17 s instead of 5.28 s in NCHW on a 2-core AVX512 CPU, with the
    same output to 1e-6. The result is returned in the ordinary (contiguous) layout."""

    def __init__(self, ops: list[dict], conv_shapes: dict[str, tuple[int, int, int]]):
        super().__init__()
        self.ops = ops
        self.convs = nn.ModuleDict()
        for name, (cout, cin, k) in conv_shapes.items():
            self.convs[name] = nn.Conv2d(cin, cout, k, padding=k // 2)
        last_use: dict[str, int] = {}
        for i, op in enumerate(ops):
            for src in op["inputs"]:
                last_use[src] = i
        self._free_after = [
            [src for src in set(op["inputs"]) if last_use[src] == i] for i, op in enumerate(ops)
        ]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x.contiguous(memory_format=torch.channels_last)
        vals: dict[str, torch.Tensor] = {}
        for i, op in enumerate(self.ops):
            kind, ins = op["op"], [vals[s] for s in op["inputs"]]
            if kind == "input":
                y = x
            elif kind == "conv":
                y = self.convs[op["name"]](ins[0])
                if op["relu"]:
                    y = F.relu(y)
            elif kind == "relu":
                y = F.relu(ins[0])
            elif kind == "identity":
                y = ins[0]
            elif kind == "concat":
                y = torch.cat(ins, dim=1)
            elif kind == "add":
                y = ins[0]
                for other in ins[1:]:
                    y = y + other
            elif kind == "mul":
                y = ins[0] * op["factor"]
            elif kind == "d2s":
                y = depth_to_space(ins[0], op["scale"])
            else:  # parse_graph only emits the kinds above
                raise ValueError(f"unknown op {kind!r}")
            del ins
            for src in self._free_after[i]:
                del vals[src]
            vals[op["name"]] = y
        return vals[self.ops[-1]["name"]].contiguous()


def convert(model_dir: Path, out_file: Path, *, source: str) -> None:
    """Convert ``model_dir/model.json`` (+ shards) to ``out_file`` (safetensors), atomically."""
    model_json_bytes = (model_dir / "model.json").read_bytes()
    model_json = json.loads(model_json_bytes)
    ops, kernels = parse_graph(model_json)
    weights = read_weights(model_dir, model_json)
    tensors: dict[str, torch.Tensor] = {}
    for name, ks in kernels.items():
        k, b = weights.pop(f"{name}/kernel", None), weights.pop(f"{name}/bias", None)
        if k is None or b is None:
            raise TfjsConversionError(f"weights of conv {name!r} missing from the manifest")
        if k.shape[:2] != ks or k.shape[3] != b.shape[0]:
            raise TfjsConversionError(f"conv {name!r} kernel shape {k.shape} mismatch")
        tensors[f"{name}.weight"] = torch.from_numpy(k).permute(3, 2, 0, 1).contiguous()
        tensors[f"{name}.bias"] = torch.from_numpy(b).contiguous()
    if weights:
        raise TfjsConversionError(f"unused weights in the manifest: {sorted(weights)[:5]}")
    meta = {
        "format": FORMAT,
        "graph": json.dumps(ops, separators=(",", ":")),
        "source": source,
        "model_json_sha256": hashlib.sha256(model_json_bytes).hexdigest(),
    }
    out_file.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_file.with_name(out_file.name + ".tmp")
    save_file(tensors, str(tmp), metadata=meta)
    tmp.replace(out_file)


def read_metadata(path: Path) -> dict[str, str]:
    """The safetensors metadata of a converted file (cheap: reads only the header)."""
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as fh:
        return dict(fh.metadata() or {})


def load_converted(path: Path, device: torch.device | str = "cpu") -> TfjsGraphNet:
    """Build the :class:`TfjsGraphNet` stored in a converted safetensors file (eval mode)."""
    meta = read_metadata(path)
    if meta.get("format") != FORMAT:
        raise TfjsConversionError(f"{path.name} is not a converted TF.js graph")
    ops = json.loads(meta["graph"])
    state = load_file(str(path), device="cpu")
    shapes = {
        op["name"]: tuple(state[f"{op['name']}.weight"].shape[:3])
        for op in ops
        if op["op"] == "conv"
    }
    net = TfjsGraphNet(ops, {k: (v[0], v[1], v[2]) for k, v in shapes.items()})
    net.convs.load_state_dict({k: v for k, v in state.items()}, strict=True)
    net = net.eval().requires_grad_(False).to(device)
    return net.to(memory_format=torch.channels_last)  # type: ignore[call-overload]  # torch's stubs omit memory_format
