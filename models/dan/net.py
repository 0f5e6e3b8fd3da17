"""Single-stage Deep Alignment Network with a face/no-face head (algorithms.md sections 1.1 and 1.9)."""

from __future__ import annotations

import torch
from torch import nn

CROP = 112


def _block(cin: int, cout: int) -> list[nn.Module]:
    layers: list[nn.Module] = []
    for i in range(2):
        layers += [
            nn.Conv2d(cin if i == 0 else cout, cout, 3, padding=1, bias=False),
            nn.BatchNorm2d(cout),
            nn.ReLU(inplace=True),
        ]
    layers.append(nn.MaxPool2d(2))
    return layers


class Dan(nn.Module):
    """VGG-style body 4 x (2 x conv3x3-BN-ReLU, maxpool) -> dropout -> fc1 256 (BN, ReLU) -> 136 offsets.

    `width` multiplies the conv channel counts (1.0 = the paper's 64/128/256/512). The landmark output is
    the offset added to the mean shape (crop pixels). The face head is a 256 -> 2 linear layer on fc1 whose
    softmax component 1 is the face probability.

    Input normalisation (per-pixel mean/std over the training crops) lives in the module as buffers so the
    exported graph takes raw pixels.
    """

    def __init__(self, mean_shape: torch.Tensor, width: float = 1.0, fc: int = 256):
        super().__init__()
        chans = [max(8, int(round(c * width))) for c in (64, 128, 256, 512)]
        layers: list[nn.Module] = []
        cin = 1
        for c in chans:
            layers += _block(cin, c)
            cin = c
        self.body = nn.Sequential(*layers)
        self.dropout = nn.Dropout(0.5)
        self.fc1 = nn.Linear(cin * 7 * 7, fc, bias=False)
        self.bn1 = nn.BatchNorm1d(fc)
        self.out = nn.Linear(fc, 136)
        self.face = nn.Linear(fc, 2)
        self.width = width
        self.register_buffer("mean_shape", mean_shape.reshape(1, 68, 2).float().clone())
        self.register_buffer("pix_mean", torch.zeros(1, 1, CROP, CROP))
        self.register_buffer("pix_std", torch.ones(1, 1, CROP, CROP))
        gain = nn.init.calculate_gain("relu")
        for m in self.modules():
            if isinstance(m, (nn.Conv2d, nn.Linear)):
                nn.init.xavier_uniform_(m.weight, gain=gain)
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
        nn.init.zeros_(self.out.weight)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        x = (x.float() - self.pix_mean) / self.pix_std
        x = self.body(x)
        x = torch.flatten(x, 1)
        x = self.dropout(x)
        return torch.relu(self.bn1(self.fc1(x)))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """x: [N,1,112,112] pixels (0..255, any dtype). Returns (landmarks [N,68,2] crop px, face logits [N,2])."""
        h = self.features(x)
        lm = self.out(h).float().reshape(-1, 68, 2) + self.mean_shape
        return lm, self.face(h).float()


class DanExport(nn.Module):
    """The exported graph: uint8 pixels in, landmarks and face probability out.

    With `mirror` (test-time augmentation), the net also runs on the horizontally mirrored crop; its landmarks
    are mapped back (68-point left/right swap, x -> CROP - x: the mirror axis is the mean shape's, x = 56) and averaged with the direct ones, and the
    two face probabilities are averaged. Twice the inference cost."""

    def __init__(self, net: Dan, mirror: bool = False, swap: list[int] | None = None):
        super().__init__()
        self.net = net
        self.mirror = mirror
        if mirror and swap is None:
            raise ValueError("mirror export needs the landmark swap")
        self.register_buffer("swap", torch.tensor(swap if swap is not None else [], dtype=torch.long))

    def forward(self, pixels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = pixels.float()
        lm, logits = self.net(x)
        p = torch.softmax(logits, dim=1)[:, 1]
        if not self.mirror:
            return lm, p
        # Mirrored about the mean shape's axis x = CROP / 2 (u -> CROP - u; see train.mirror_crop).
        xm = torch.nn.functional.pad(torch.flip(x, dims=[3]), (1, 0))[..., :CROP]
        lm_m, logits_m = self.net(xm)
        lm_m = lm_m.index_select(1, self.swap)
        lm_m = torch.stack([CROP - lm_m[..., 0], lm_m[..., 1]], dim=-1)
        return 0.5 * (lm + lm_m), 0.5 * (p + torch.softmax(logits_m, dim=1)[:, 1])
