"""The former name of `simloader.records` (what a batch records, `record=`): the same module,
so every name it had (`parse`, `Camera`, `Observation`, `State`, `Field`, `Sensor`,
`CameraImage`, `DEFAULT`, ...) keeps working."""

import sys

from simloader import records

sys.modules[__name__] = records
