"""Building blocks named as in the supplement (Fig. 2): ConvBlock, ResBlock; and channel attention."""

from torch import nn


class ConvBlock(nn.Sequential):
    """Convolution followed by ReLU."""

    def __init__(self, cin: int, cout: int, kernel: int = 3, stride: int = 1):
        super().__init__(nn.Conv2d(cin, cout, kernel, stride, kernel // 2), nn.ReLU(inplace=True))


class ResBlock(nn.Module):
    """conv-ReLU-conv plus identity, no normalisation (EDSR's residual block)."""

    def __init__(self, features: int):
        super().__init__()
        self.body = nn.Sequential(nn.Conv2d(features, features, 3, 1, 1), nn.ReLU(inplace=True),
                                  nn.Conv2d(features, features, 3, 1, 1))

    def forward(self, x):
        return x + self.body(x)


class ChannelAttention(nn.Module):
    """Squeeze-and-excitation over channels: a global view that reweights local features."""

    def __init__(self, channels: int, reduction: int = 4):
        super().__init__()
        self.gate = nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Conv2d(channels, channels // reduction, 1),
                                  nn.ReLU(inplace=True), nn.Conv2d(channels // reduction, channels, 1), nn.Sigmoid())

    def forward(self, x):
        return x * self.gate(x)
