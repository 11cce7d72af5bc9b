"""The learned prior: the runtime prior (``prior``), its UNet (``unet``) and the pipeline that
makes its weights (``data``, ``training``, ``evaluation``)."""
