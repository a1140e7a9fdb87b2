"""The DUSt3R family (DUSt3R, MASt3R, MonST3R): the network and its official checkpoint files.

- `checkpoint`: safe reading of official checkpoint files (`args.model` parsed, never executed).
- `vit_encoder`: the ViT encoder (2-D RoPE), DynPT's frozen 3D-aware encoder.
- `net`: the whole pointmap network (encoder, two cross-attending decoders, linear or DPT heads).
C4D's use of the network (its pointmap source, its trainer) lives in `c4d_pipeline`.
"""
