"""Exporters from PyTorch foundation models to the ONNX model folders the runtime classes read.

Each exporter writes one folder: the ONNX files, any file the runtime needs beside them (CLIP's BPE
vocabulary) and ``manifest.json`` (:mod:`encoders.manifest`), written last, so a folder without a
manifest is an export that did not finish. Exporters need the optional ``export`` extra
(``pip install 'langfield[export]'``: open_clip_torch, segment-anything, transformers, onnx,
onnxscript); the runtime needs only onnxruntime.

- :func:`encoders.export.clip.export_clip`: OpenCLIP image and text towers;
- :func:`encoders.export.sam.export_sam`: SAM's image encoder and mask decoder;
- :func:`encoders.export.depth.export_depth`: a transformers DPT or Depth Anything model;
- :func:`encoders.export.refiner.export_refiner`: any image-to-image ``torch.nn.Module`` (a refiner of
  rendered views; no weights ship with langfield).
"""
