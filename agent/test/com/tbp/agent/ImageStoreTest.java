package com.tbp.agent;

import static org.junit.Assert.assertEquals;
import static org.junit.Assert.assertFalse;
import static org.junit.Assert.assertTrue;
import static org.junit.Assert.fail;

import java.io.File;
import java.io.IOException;
import java.nio.ByteBuffer;
import java.nio.file.Files;
import org.junit.Test;

public class ImageStoreTest {

    @Test
    public void numbersOnFromTheHighestImageAndRemovesPartialOnes() throws Exception {
        File folder = Fakes.folder();
        assertTrue(folder.mkdirs());
        Files.write(new File(folder, "IMG_00041.jpg").toPath(), new byte[] {1});
        Files.write(new File(folder, "IMG_00007.jpg").toPath(), new byte[] {1});
        Files.write(new File(folder, ".part-IMG_00042.jpg").toPath(), new byte[] {1});
        ImageStore store = new ImageStore(folder, new Fakes.Disk());
        store.open();
        assertFalse(new File(folder, ".part-IMG_00042.jpg").exists());
        assertEquals("/sdcard/DCIM/tbp/IMG_00042.jpg", store.write(ByteBuffer.wrap(new byte[3])).path);
        Files.write(new File(folder, "IMG_00043.jpg").toPath(), new byte[] {9});  // someone else's file
        ImageStore.Stored next = store.write(ByteBuffer.wrap(new byte[4]));
        assertEquals("/sdcard/DCIM/tbp/IMG_00044.jpg", next.path);
        assertEquals(4, next.size);
        assertEquals(1, Files.size(new File(folder, "IMG_00043.jpg").toPath()));
    }

    @Test
    public void aFailedWriteLeavesNoFile() throws IOException {
        File folder = Fakes.folder();
        ImageStore store = new ImageStore(folder, new Fakes.Disk());
        store.open();
        assertTrue(folder.setWritable(false));
        try {
            store.write(ByteBuffer.wrap(new byte[10]));
            if (!"root".equals(System.getProperty("user.name"))) {
                fail("wrote into a read-only folder");
            }
        } catch (AgentError e) {
            assertEquals(ErrorCode.CAPTURE_FAILED, e.code);
            assertEquals(0, folder.list().length);
        } finally {
            assertTrue(folder.setWritable(true));
        }
    }
}
