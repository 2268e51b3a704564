"""Layer ``imaging``: images built from cached views (image specs, crops, compositing,
backgrounds), cached views on the device, renders of every kind through the field, contact
sheets, PNG output and image-quality figures (PSNR, SSIM over object pixels)."""
