# Read by cpack: the package's unit and paths assume the /usr prefix.
if(CPACK_GENERATOR STREQUAL "DEB" AND NOT CPACK_KEYFRAMED_PREFIX STREQUAL "/usr")
  message(FATAL_ERROR "the .deb needs a build configured with -DCMAKE_INSTALL_PREFIX=/usr "
                      "(this one has ${CPACK_KEYFRAMED_PREFIX})")
endif()
