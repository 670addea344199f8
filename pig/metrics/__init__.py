"""Image metrics: PSNR, SSIM, LPIPS, FID."""
