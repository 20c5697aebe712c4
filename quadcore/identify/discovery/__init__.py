"""Term discovery: the terms the effect library lacks, by sparse regression of the model's
residual on a library of candidate terms, cross-validated over flights.

The modules, each importing only from those above it in this list:

- :mod:`~quadcore.identify.discovery.terms`: the candidate library (variables, terms, units, values
  over a flight, the tautology guard, the literature's names);
- :mod:`~quadcore.identify.discovery.grams`: the Gram matrices' columns, one flight's matrices and
  their sums over the folds;
- :mod:`~quadcore.identify.discovery.library_stats`: a flight's matrices stored under the data root;
- :mod:`~quadcore.identify.discovery.accumulate`: the flights' sums, from rows or stored statistics;
- :mod:`~quadcore.identify.discovery.results`: the typed result (the ``--json`` document);
- :mod:`~quadcore.identify.discovery.select`: the selection per axis and :func:`discover`;
- :mod:`~quadcore.identify.discovery.writer`: the kept terms as a linear effect plugin.
"""

from quadcore.identify.discovery import library_stats
from quadcore.identify.discovery.results import DiscoveredTerm, Discovery
from quadcore.identify.discovery.select import discover
from quadcore.identify.discovery.writer import NAME_RE, DiscoveredEffect, WrittenEffect, write_effect

# What callers outside discovery use; DiscoveredEffect is what the modules write_effect writes import.
__all__ = ["NAME_RE", "DiscoveredEffect", "DiscoveredTerm", "Discovery", "WrittenEffect", "discover",
           "library_stats", "write_effect"]
