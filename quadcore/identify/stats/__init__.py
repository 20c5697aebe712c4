"""A flight's statistics: the profiles of its one-parameter nonlinear effects (:mod:`.profiles`),
and the Gram sums, their layout, the record they are stored in and its cache
(:mod:`.sufficient`): the one place a flight's rows become statistics."""
