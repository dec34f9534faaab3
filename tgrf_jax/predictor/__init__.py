"""Training the learned trajectory predictor (GST): collect episodes from the env (`data`), fit and evaluate new
weights (`train`); `tgrf-predictor` is the command. The model itself, and its inference inside the env, is
`tgrf_jax.env.gst`.
"""
