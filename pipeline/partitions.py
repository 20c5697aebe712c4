"""One dynamic partition per flight; the key is the raw log's file name."""

import dagster as dg

flights = dg.DynamicPartitionsDefinition(name="flights")
