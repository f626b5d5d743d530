#!/usr/bin/env python3
"""Golden PSNR / SSIM values for the metrics crate's image metrics, computed with scikit-image.

Used once to write the constants of `real_data_psnr_ssim_match_scikit_image`
(metrics/src/image.rs). JPEG decoders disagree by a few grey levels (chroma
upsampling), so the frames are first decoded by mac-ego3d's own reader and written losslessly:

    target/debug/mac-ego3d dataset frame ../shared/datasets/7scenes-redkitchen --frame 0 --rgb /tmp/a.png
    target/debug/mac-ego3d dataset frame ../shared/datasets/7scenes-redkitchen --frame 10 --rgb /tmp/b.png
    pip install scikit-image && python3 scripts/golden_image_metrics.py /tmp/a.png /tmp/b.png

`ssim_valid` is scikit-image's structural_similarity (Gaussian 11x11, sigma 1.5,
use_sample_covariance=False, data range 1, mean over the region where the window fits).
`ssim` is the 3DGS variant (zero-padded local statistics, mean over every pixel), computed here
with scipy.ndimage on the same formula.
"""
import sys

import numpy as np
from PIL import Image
from scipy import ndimage
from skimage.metrics import peak_signal_noise_ratio, structural_similarity


def ssim_zero_padded(a, b, sigma=1.5, k1=0.01, k2=0.03):
    radius = 5
    x = np.arange(-radius, radius + 1)
    g = np.exp(-(x**2) / (2 * sigma**2))
    g /= g.sum()
    window = np.outer(g, g)

    def blur(p):
        return ndimage.correlate(p, window, mode="constant", cval=0.0)

    c1, c2 = k1**2, k2**2
    values = []
    for c in range(a.shape[2]):
        x_, y_ = a[..., c], b[..., c]
        mx, my = blur(x_), blur(y_)
        vx = blur(x_ * x_) - mx * mx
        vy = blur(y_ * y_) - my * my
        cxy = blur(x_ * y_) - mx * my
        s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
        values.append(s.mean())
    return float(np.mean(values))


def main():
    a = np.asarray(Image.open(sys.argv[1]).convert("RGB"), dtype=np.float64) / 255.0
    b = np.asarray(Image.open(sys.argv[2]).convert("RGB"), dtype=np.float64) / 255.0
    psnr = peak_signal_noise_ratio(a, b, data_range=1.0)
    ssim_valid = structural_similarity(
        a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0, channel_axis=2
    )
    print(f"psnr {psnr:.10f}\nssim {ssim_zero_padded(a, b):.10f}\nssim_valid {ssim_valid:.10f}")


if __name__ == "__main__":
    main()
