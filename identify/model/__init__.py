"""The model: parameter specs and presets (Table II), friction and aging laws, the symbolic
hybrid model, the unmodelled effects, and the cache of compiled CasADi Functions."""
