// Box files: written by the box-file work (see interest.h for the API).
#include "interest.h"
