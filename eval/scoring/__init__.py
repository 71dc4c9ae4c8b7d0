"""How a prediction is scored and shown: per-image errors and their summaries (:mod:`.metrics`),
the markdown tables (:mod:`.tables`) and the figures (:mod:`.plots`)."""
