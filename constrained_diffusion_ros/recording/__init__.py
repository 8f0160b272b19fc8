"""Trial bags: written by the recorder node, read back by `trial`, `replay` and the figures,
and recovered after a kill (`recover_bag`); apart from evaluation, which only reads them."""
