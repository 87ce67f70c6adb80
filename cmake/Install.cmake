# Installation layout and the Debian package (cpack -G DEB, or the `package` target).
# Paths are for prefix /usr: binary in /usr/bin, unit and sysusers.d entry under
# /usr/lib, configuration in /etc/keyframed (a conffile), docs in /usr/share/doc.
# Stage with DESTDIR: `DESTDIR=/tmp/stage cmake --install build/release`.

# The unit names /usr/bin/keyframed; follow the prefix when it is another one.
set(_unit_src "${PROJECT_SOURCE_DIR}/systemd/keyframed.service")
set_property(DIRECTORY APPEND PROPERTY CMAKE_CONFIGURE_DEPENDS "${_unit_src}")
file(READ "${_unit_src}" _unit)
string(REPLACE "/usr/bin/keyframed" "${CMAKE_INSTALL_FULL_BINDIR}/keyframed" _unit "${_unit}")
file(WRITE "${CMAKE_BINARY_DIR}/systemd/keyframed.service" "${_unit}")

install(FILES "${CMAKE_BINARY_DIR}/systemd/keyframed.service" DESTINATION lib/systemd/system)
install(FILES systemd/keyframed.sysusers DESTINATION lib/sysusers.d RENAME keyframed.conf)
install(FILES config/keyframed.toml DESTINATION "${KEYFRAMED_CONFIG_DIR}")
install(DIRECTORY DESTINATION "${KEYFRAMED_CONFIG_DIR}/conf.d")
install(FILES README.md docs/configuration.md docs/design.md docs/formats.md docs/performance.md
              docs/deploy.md docs/capture.md
        DESTINATION "${CMAKE_INSTALL_DOCDIR}")
install(FILES config/camera-example.yaml config/camera-fisheye-example.yaml
        DESTINATION "${CMAKE_INSTALL_DOCDIR}/examples")

# Debian package.
set(CPACK_GENERATOR DEB)
set(CPACK_PACKAGE_NAME keyframed)
set(CPACK_PACKAGE_VERSION "${PROJECT_VERSION}")
set(CPACK_PACKAGE_CONTACT "keyframed developers <keyframed@users.noreply.github.com>")
set(CPACK_PACKAGE_DESCRIPTION_SUMMARY
    "keyframe selection daemon for UAV companion computers (sharp, overlapping, geotagged)")
set(CPACK_DEBIAN_FILE_NAME DEB-DEFAULT)  # keyframed_<version>_<arch>.deb
set(CPACK_DEBIAN_PACKAGE_SECTION video)
# postinst makes the user with systemd-sysusers, or adduser where systemd is absent.
set(CPACK_DEBIAN_PACKAGE_DEPENDS "systemd | adduser")
set(CPACK_DEBIAN_PACKAGE_SHLIBDEPS ON)  # the rest of Depends: from dpkg-shlibdeps
# libcamera's IPA modules: a Pi camera does not start without them (Debian's
# libcamera0.0.3 only suggests libcamera-ipa).
if(KEYFRAMED_WITH_LIBCAMERA)
  set(CPACK_DEBIAN_PACKAGE_RECOMMENDS "systemd, libcamera-ipa")
else()
  set(CPACK_DEBIAN_PACKAGE_RECOMMENDS "systemd")
endif()
set(CPACK_STRIP_FILES ON)
# /etc is outside the prefix: install through DESTDIR so absolute paths land in the package.
set(CPACK_SET_DESTDIR ON)
set(CPACK_KEYFRAMED_PREFIX "${CMAKE_INSTALL_PREFIX}")
set(CPACK_PROJECT_CONFIG_FILE "${PROJECT_SOURCE_DIR}/cmake/CPackProject.cmake")
configure_file(packaging/deb/conffiles.in "${CMAKE_BINARY_DIR}/deb/conffiles" @ONLY)
foreach(_script postinst prerm postrm)
  configure_file("packaging/deb/${_script}" "${CMAKE_BINARY_DIR}/deb/${_script}" COPYONLY)
endforeach()
set(CPACK_DEBIAN_PACKAGE_CONTROL_EXTRA
    "${CMAKE_BINARY_DIR}/deb/conffiles;${CMAKE_BINARY_DIR}/deb/postinst;${CMAKE_BINARY_DIR}/deb/prerm;${CMAKE_BINARY_DIR}/deb/postrm")
set(CPACK_DEBIAN_PACKAGE_CONTROL_STRICT_PERMISSION ON)
include(CPack)
