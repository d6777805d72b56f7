-- Schema version 6: the name of the API key that opened a trip (issue 42, defect 8). Only
-- that key or an admin may post frames to the trip or close it. NULL: opened without access
-- control, or before this version (any vehicle key may then extend or close it, as before).
ALTER TABLE trips ADD COLUMN owner TEXT;
