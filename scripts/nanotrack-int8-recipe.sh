# Sourced by int8-spread.sh and orin-estimate.sh: NanoTrack v2's int8 recipe, the README's
# ("int8"): the `prl quantize` options that go with `--plan` and `--calib building4`.
nanotrack_int8_recipe=(--frames-per-seq 128 --method minmax --min-macs 1000000 --min-out-channels 16 --budget 6)
# The faster plan for CPUs with an integer depthwise kernel (AVX-512 VNNI with VBMI; aarch64's
# dot product, the Orin): depthwise layers integer too, least-squared-error ranges.
nanotrack_int8_dw_recipe=(--frames-per-seq 128 --method mse --min-macs 1000000 --min-out-channels 16 --depthwise --budget 4)
